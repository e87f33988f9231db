"""The render op cut at the projected splats (warpgs/render/splats.py) renders and differentiates what
`rasterize` does, and model-parallel rendering (warpgs/render/sharded.py) over two gloo processes, each holding
half of the primitives and one camera, gives each camera the image and every primitive the gradient of one
process rendering both cameras from all primitives."""
import pytest
import torch

from gloo_helpers import run_two_ranks
from random_scenes import look_at, random_scene
from warpgs import rasterize
from warpgs.render.splats import Splats, blend_splats, project_splats

PARAMS = ("means", "quats", "scales", "opacities", "colors", "features")
OUTPUTS = ("rgb", "alpha", "depth", "inv_depth", "features")


def _leaves(scene):
    return {k: scene[k].float().clone().requires_grad_(True) for k in PARAMS if scene[k] is not None}


def _loss(out, seed):
    """A fixed random linear function of every output (so each output's adjoint is exercised)."""
    g = torch.Generator().manual_seed(seed)
    total = 0.0
    for name in OUTPUTS:
        img = getattr(out, name)
        total = total + (img * torch.rand(img.shape, generator=g)).sum()
    return total


def _render_whole(p, scene, viewmat, track_means2d=False):
    return rasterize(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"], viewmat.float(),
                     scene["K"].float(), scene["width"], scene["height"], sh_degree=scene["sh_degree"],
                     features=p["features"], outputs=OUTPUTS, track_means2d=track_means2d)


def test_projecting_then_blending_is_rasterize():
    scene = random_scene(n=64, sh_degree=2, num_features=3, seed=3)
    ref, cut = _leaves(scene), _leaves(scene)
    want = _render_whole(ref, scene, scene["viewmat"])
    splats = project_splats(cut["means"], cut["quats"], cut["scales"], cut["opacities"], cut["colors"],
                            scene["viewmat"].float(), scene["K"].float(), scene["width"], scene["height"],
                            sh_degree=scene["sh_degree"], features=cut["features"])
    assert 0 < int(splats.valid.sum()) < 64  # the scene has a primitive behind the camera
    got = blend_splats(Splats.unpack(splats.select(splats.valid).pack()), scene["width"], scene["height"],
                       outputs=OUTPUTS)
    for name in OUTPUTS:
        torch.testing.assert_close(getattr(got, name), getattr(want, name), atol=1e-5, rtol=1e-5, msg=name)
    _loss(want, 0).backward()
    _loss(got, 0).backward()
    for k in PARAMS:
        assert cut[k].grad is not None and torch.isfinite(cut[k].grad).all(), k
        assert ref[k].grad.abs().sum() > 0, k
        torch.testing.assert_close(cut[k].grad, ref[k].grad, atol=1e-4, rtol=1e-4, msg=k)


def test_the_split_blend_uses_the_calls_adjoint_kernel(monkeypatch):
    # raster_options(backward_kernel=...) picks the GPU blend adjoint; the split op must pass it on as the whole
    # op does (the gradients agree either way, so only the argument shows it).
    from warpgs.render import fast_pipeline
    from warpgs.render.defaults import raster_options
    seen = []
    real = fast_pipeline.blend_backward

    def spy(*args, **kwargs):
        seen.append(args[10] if len(args) > 10 else kwargs.get("backward_kernel", "warp_sums"))
        return real(*args, **kwargs)

    monkeypatch.setattr(fast_pipeline, "blend_backward", spy)
    scene = random_scene(n=32, num_features=2, seed=5)
    whole, cut = _leaves(scene), _leaves(scene)
    with raster_options(backward_kernel="block"):
        _render_whole(whole, scene, scene["viewmat"]).rgb.sum().backward()
        splats = project_splats(cut["means"], cut["quats"], cut["scales"], cut["opacities"], cut["colors"],
                                scene["viewmat"].float(), scene["K"].float(), scene["width"], scene["height"])
        blend_splats(Splats.unpack(splats.select(splats.valid).pack()), scene["width"], scene["height"],
                     outputs=("rgb",)).rgb.sum().backward()
    assert seen == ["block", "block"]


def test_blend_splats_refuses_unknown_outputs():
    with pytest.raises(ValueError, match="outputs"):
        blend_splats(Splats.unpack(torch.zeros(0, 13)), 8, 8, outputs=("rgb", "normals"))


WORKER = r'''
import sys, torch, torch.distributed as dist
from gloo_helpers import end_worker
from random_scenes import random_scene
from warpgs.render.sharded import render_sharded
dist.init_process_group("gloo")
rank = dist.get_rank()
payload = torch.load(sys.argv[1])
scene, cams, outputs = payload["scene"], payload["viewmats"], payload["outputs"]
mine = slice(0, 40) if rank == 0 else slice(40, None)  # unequal shares; rank 1's has the one behind camera 1
p = {k: scene[k][mine].float().clone().requires_grad_(True) for k in payload["params"]}
out = render_sharded(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"], cams.float(),
                     scene["K"].float().expand(2, 3, 3), scene["width"], scene["height"],
                     sh_degree=scene["sh_degree"], features=p["features"], outputs=outputs, track_means2d=True)
g = torch.Generator().manual_seed(100 + rank)
loss = sum((getattr(out, n) * torch.rand(getattr(out, n).shape, generator=g)).sum() for n in outputs)
loss.backward()
torch.save({"images": {n: getattr(out, n).detach() for n in outputs}, "grads": {k: v.grad for k, v in p.items()},
            "means2d_grad": out.means2d.grad, "sent": out.sent, "seen": out.seen},
           sys.argv[2] + f".rank{rank}")
end_worker()
'''


def test_two_ranks_with_half_the_primitives_each_render_and_differentiate_as_one(tmp_path):
    scene = random_scene(n=72, sh_degree=1, num_features=2, seed=5)
    viewmats = torch.stack([scene["viewmat"], look_at((1.5, -0.5, -3.5), (0.0, 0.2, 0.0))])
    torch.save({"scene": scene, "viewmats": viewmats, "outputs": OUTPUTS, "params": PARAMS}, tmp_path / "in.pt")
    run_two_ranks(WORKER, [tmp_path / "in.pt", tmp_path / "out"], tmp_path)
    ranks = [torch.load(tmp_path / f"out.rank{r}") for r in (0, 1)]

    # One process: both cameras from all primitives, the same two losses.
    whole = _leaves(scene)
    total = 0.0
    probes = []
    for r in (0, 1):
        out = _render_whole(whole, scene, viewmats[r], track_means2d=True)
        probes.append(out)
        for name in OUTPUTS:
            torch.testing.assert_close(ranks[r]["images"][name], getattr(out, name), atol=1e-5, rtol=1e-5,
                                       msg=f"camera {r}: {name}")
        g = torch.Generator().manual_seed(100 + r)
        total = total + sum((getattr(out, n) * torch.rand(getattr(out, n).shape, generator=g)).sum()
                            for n in OUTPUTS)
    total.backward()
    for k in PARAMS:
        got = torch.cat([ranks[0]["grads"][k], ranks[1]["grads"][k]])
        assert whole[k].grad.abs().sum() > 0, k
        torch.testing.assert_close(got, whole[k].grad, atol=1e-4, rtol=1e-4, msg=k)
    # Densification's inputs per owner: each camera's dL/dmeans2d and footprint-on-screen mask of its own rows.
    for cam in (0, 1):
        g = torch.cat([ranks[0]["means2d_grad"][cam], ranks[1]["means2d_grad"][cam]])
        torch.testing.assert_close(g, probes[cam].means2d.grad, atol=1e-4, rtol=1e-4, msg=f"means2d, camera {cam}")
        sent = torch.cat([ranks[0]["sent"][cam], ranks[1]["sent"][cam]])
        assert bool(sent[probes[cam].visible].all())
        # What each camera's blend binned, returned to the owners, is exactly one process's visibility.
        seen = torch.cat([ranks[0]["seen"][cam], ranks[1]["seen"][cam]])
        assert torch.equal(seen, probes[cam].visible) and 0 < int(seen.sum()) < int(sent.sum()) + 1


@pytest.mark.parametrize("rows", [0, 1, 2])
def test_a_handful_of_splats_blend_and_differentiate(rows):
    # One row of packed splats is a slice torch calls contiguous with the packed row stride (it broke Warp's grad).
    scene = random_scene(n=24, seed=9)
    p = _leaves(scene)
    splats = project_splats(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"], scene["viewmat"].float(),
                            scene["K"].float(), scene["width"], scene["height"])
    centre = splats.means2d.detach()
    on_screen = (centre[:, 0] > 0) & (centre[:, 0] < scene["width"]) & (centre[:, 1] > 0) & (centre[:, 1] < scene["height"])
    keep = (splats.valid & on_screen).nonzero().squeeze(1)[:rows]
    assert len(keep) == rows
    out = blend_splats(Splats.unpack(splats.select(keep).pack()), scene["width"], scene["height"],
                       outputs=("rgb", "alpha", "depth"))
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    assert p["means"].grad is not None and torch.isfinite(p["means"].grad).all()
    touched = p["opacities"].grad  # None when no splat reached the blend
    assert (0 if touched is None else int((touched != 0).sum())) <= rows
    if rows:
        assert int((touched != 0).sum()) > 0
    with pytest.raises(ValueError, match="no feature columns"):
        blend_splats(Splats.unpack(splats.select(keep).pack()), 8, 8, outputs=("rgb", "features"))


def test_only_splats_that_can_reach_the_image_are_sent():
    from warpgs.render.sharded import reaches_image

    scene = random_scene(n=64, seed=3, num_features=1)
    p = _leaves(scene)
    splats = project_splats(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"], scene["viewmat"].float(),
                            scene["K"].float(), scene["width"], scene["height"])
    send = reaches_image(splats, scene["width"], scene["height"])
    used = _render_whole(p, scene, scene["viewmat"]).visible  # what the binning kept
    assert bool(send[used].all())  # nothing the blend uses is left behind
    assert not bool(send[0]) and not bool(send[1])  # behind the camera; far off-screen right
    assert int(send.sum()) < int(splats.valid.sum())


def test_bad_arguments_are_named():
    scene = random_scene(n=8)
    p = _leaves(scene)
    with pytest.raises(ValueError, match="quats"):
        project_splats(p["means"], p["quats"][:, :3], p["scales"], p["opacities"], p["colors"],
                       scene["viewmat"].float(), scene["K"].float(), 40, 30)
    splats = project_splats(p["means"], p["quats"], p["scales"], p["opacities"], p["colors"],
                            scene["viewmat"].float(), scene["K"].float(), 40, 30)
    with pytest.raises(ValueError, match="alpha_min"):
        blend_splats(splats, 40, 30, alpha_min=0.0)
