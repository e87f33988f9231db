"""Forward values of the Warp surfel (2DGS) rasterizer against the float64 brute-force reference."""
import pytest
import torch

from reference_surfels import ALL_OUTPUTS, random_surfel_scene, render_surfels_ours, render_surfels_ref

TOL = 1e-4


def max_err(ours, ref, name):
    return (getattr(ours, name).double() - ref[name]).abs().max().item()


def check_all(ours, ref):
    for name in ("rgb", "alpha", "inv_depth", "normal", "features"):
        assert max_err(ours, ref, name) <= TOL, name
    # Depths are in scene units (up to ~7 here): compare relative to the depth scale.
    for name in ("depth", "median_depth"):
        assert max_err(ours, ref, name) <= TOL * ref[name].abs().max().item(), name
    # The 2DGS distortion is tiny in absolute terms (NDC depth): compare relative to its largest value.
    assert ref["distortion"].max() > 0
    assert max_err(ours, ref, "distortion") <= TOL * ref["distortion"].max().item()


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("sh_degree", [None, 1, 3])
def test_forward_matches_reference(seed, sh_degree):
    scene = random_surfel_scene(n=48, seed=seed, sh_degree=sh_degree, num_features=3)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    ours = render_surfels_ours(scene, ALL_OUTPUTS, background=bg)
    ref = render_surfels_ref(scene, background=bg)
    assert ref["alpha"].max() > 0.5, "scene should cover the image substantially"
    check_all(ours, ref)


@pytest.mark.parametrize("tile_size", [1, 3, 16])
def test_footprints_cover_large_tilted_surfels_at_any_tile_size(tile_size):
    # Big disks seen at steep angles: a footprint that missed a pixel would show up at tile size 1.
    scene = random_surfel_scene(n=48, seed=4, num_features=2)
    scene["scales"] *= 2.5
    ours = render_surfels_ours(scene, ALL_OUTPUTS, tile_size=tile_size)
    check_all(ours, render_surfels_ref(scene))


def test_result_does_not_depend_on_tile_size():
    scene = random_surfel_scene(n=48, seed=5)
    outs = [render_surfels_ours(scene, ALL_OUTPUTS[:-1], tile_size=t) for t in (8, 16, 32)]
    for o in outs[1:]:
        for name in ALL_OUTPUTS[:-1]:
            assert torch.equal(getattr(o, name), getattr(outs[0], name)), name


def test_only_requested_outputs_are_computed_and_subsets_agree():
    scene = random_surfel_scene(n=32, seed=6, num_features=2)
    full = render_surfels_ours(scene, ALL_OUTPUTS)
    for name in ALL_OUTPUTS:
        one = render_surfels_ours(scene, (name,))
        assert torch.equal(getattr(one, name), getattr(full, name)), name
        for other in ALL_OUTPUTS:
            if other != name:
                assert getattr(one, other) is None, (name, other)


def test_culled_surfels_are_not_visible():
    scene = random_surfel_scene(n=48, seed=0)
    out = render_surfels_ours(scene, ("alpha",))
    assert not out.visible[0]  # behind the camera
    assert not out.visible[1]  # far off-screen
    assert out.visible[3:8].all()  # the stack, the nearly edge-on and the back-facing surfel


def test_batch_of_cameras_equals_single_renders():
    from random_scenes import look_at
    from warpgs import rasterize_surfels

    scene = random_surfel_scene(n=32, seed=7)
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    views = torch.stack([s["viewmat"], look_at((1.0, 0.0, -4.0), (0.0, 0.0, 0.0)).float()])
    Ks = torch.stack([s["K"], s["K"]])
    outputs = ("rgb", "depth", "normal", "median_depth", "distortion")
    args = (s["means"], s["quats"], s["scales"], s["opacities"], s["colors"])
    batch = rasterize_surfels(*args, views, Ks, s["width"], s["height"], outputs=outputs)
    assert batch.normal.shape == (2, s["height"], s["width"], 3)
    for b in range(2):
        single = rasterize_surfels(*args, views[b], Ks[b], s["width"], s["height"], outputs=outputs)
        for name in outputs:
            assert torch.equal(getattr(batch, name)[b], getattr(single, name)), name
