"""The lean host path (render/fast_pipeline.py: workspace, recorded launches, the per-warp GPU adjoint) renders and
differentiates as the per-call op of tests/legacy_raster.py (the oracle: same kernels, simple host side) does, and
reusing scratch memory across calls never corrupts a render whose backward is still pending."""
import os

import pytest
import torch

from legacy_raster import rasterize_legacy
from random_scenes import look_at, random_scene
from raster_helpers import DEVICE, assert_same_result as _assert_same, op_for, op_leaves, op_scene
from warpgs import rasterize
from warpgs.render.defaults import raster_options

INPUTS = ("means", "quats", "scales", "opacities", "colors", "features", "viewmat", "K")
COOPERATIVE = DEVICE != "cpu" or os.environ.get("WARPGS_CPU_COOPERATIVE") == "1"


def _exact(options) -> bool:
    """The same kernels run on both paths, so on the CPU the results agree to the last bit; GPU atomics (their order
    differs between runs) and the per-warp adjoint (it sums in another order) agree to float rounding."""
    return DEVICE == "cpu" and not (COOPERATIVE and options.get("backward_kernel", "block") != "block")


def _exact_grad(options, name) -> bool:
    """As _exact, but with the cooperative kernels the camera's gradients are summed from one row per Gaussian
    (render/camera_rows.py) where the oracle adds them with atomics, so they agree to float rounding."""
    return _exact(options) and not (COOPERATIVE and name in ("viewmat", "K"))


def _leaves(scene, requires_grad=True):
    return {k: (scene[k].detach().float().to(DEVICE).requires_grad_(requires_grad)
                if scene.get(k) is not None else None) for k in INPUTS}


def _render(scene, leaves, outputs, op=rasterize, **kw):
    return op(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
                     leaves["viewmat"], leaves["K"], scene["width"], scene["height"], sh_degree=scene["sh_degree"],
                     features=leaves["features"], outputs=outputs, **kw)


def _loss(out, weights):
    return sum((getattr(out, name) * w).sum() for name, w in weights.items())


def _weights(scene, outputs, seed=0):
    g = torch.Generator().manual_seed(seed)
    channels = {"rgb": 3, "alpha": 1, "depth": 1, "inv_depth": 1, "features": 0 if scene["features"] is None
                else scene["features"].shape[1]}
    return {o: torch.randn(scene["height"], scene["width"], channels[o], generator=g).to(DEVICE) for o in outputs}


def _run(scene, outputs, options=None, op=rasterize, track_means2d=False, **kw):
    leaves = _leaves(scene)
    with raster_options(**(options or {})):
        out = _render(scene, leaves, outputs, op=op, track_means2d=track_means2d, **kw)
    _loss(out, _weights(scene, outputs)).backward()
    grads = {k: v.grad for k, v in leaves.items() if v is not None}
    if track_means2d:
        grads["means2d"] = out.means2d.grad
    return out, grads


PATHS = [dict(backward_kernel="scatter"), dict(backward_kernel="warp_sums"), dict(backward_kernel="block")]


@pytest.mark.parametrize("options", PATHS, ids=lambda o: o["backward_kernel"])
@pytest.mark.parametrize("sh_degree,num_features,tile", [(None, 0, 8), (2, 3, 8), (None, 2, 16), (1, 0, 4),
                                                         (None, 1, 32)])
def test_fast_path_matches_legacy_path(options, sh_degree, num_features, tile):
    scene = random_scene(n=60, seed=3, sh_degree=sh_degree, num_features=num_features)
    outputs = ("rgb", "alpha", "depth", "inv_depth") + (("features",) if num_features else ())
    ref, ref_grads = _run(scene, outputs, op=rasterize_legacy, track_means2d=True, tile_size=tile)
    out, grads = _run(scene, outputs, options, track_means2d=True, tile_size=tile)
    for name in outputs + ("visible",):
        _assert_same(getattr(out, name), getattr(ref, name), name)
    assert out.num_intersections == ref.num_intersections
    for name, g in ref_grads.items():
        _assert_same(grads[name], g, f"grad {name}", _exact_grad(options, name))


def test_gaussians_that_reach_no_pixel_skip_the_projection_adjoint_and_get_zero_gradients():
    """The projection adjoint runs only where the blend sent a gradient back: with a third of the Gaussians moved out
    of view, the gradients still match the oracle's full adjoint (bit for bit on the CPU), theirs are zero and the
    camera's gradient, summed over every Gaussian, is unchanged."""
    scene = random_scene(n=60, seed=3, sh_degree=2, num_features=0)
    gone = torch.arange(0, 60, 3)
    scene["means"] = scene["means"].clone()
    scene["means"][gone] += torch.tensor([60.0, 0.0, 0.0])  # far to one side: projected, culled or off screen
    outputs = ("rgb", "alpha", "depth")
    ref, ref_grads = _run(scene, outputs, op=rasterize_legacy)
    out, grads = _run(scene, outputs, PATHS[0])
    for name, g in ref_grads.items():
        _assert_same(grads[name], g, f"grad {name}", _exact_grad(PATHS[0], name))
    assert torch.all(grads["means"][gone] == 0) and torch.all(grads["colors"][gone] == 0)
    kept = torch.ones(60, dtype=torch.bool)
    kept[gone] = False
    assert grads["means"][kept].abs().sum() > 0 and grads["viewmat"].abs().sum() > 0


def test_forward_only_renders_match():
    scene = random_scene(n=60, seed=5, num_features=2)
    outputs = ("rgb", "alpha", "depth", "features")
    with torch.no_grad():
        ref = _render(scene, _leaves(scene, False), outputs, op=rasterize_legacy, tile_size=8)
        out = _render(scene, _leaves(scene, False), outputs, tile_size=8)
    for name in outputs:
        _assert_same(getattr(out, name), getattr(ref, name), name)


@pytest.mark.parametrize("op", ["gaussians", "surfels"])
def test_renders_nobody_differentiates_skip_autograd_and_match(op, monkeypatch):
    """With grad mode on but no input needing a gradient (evaluation, viewers), or grad mode off, the ops run their
    forward without the autograd Function (gaussians_fast.run_op): the same images, and nothing to differentiate."""
    from warpgs.render.gaussians_fast import FastRasterizeFunction
    from warpgs.render.surfels_fast import FastSurfelsFunction

    scene = random_scene(n=60, seed=7, num_features=2)
    if op == "surfels":
        scene = dict(scene, scales=scene["scales"][:, :2])
    render = op_for(op == "surfels")
    outputs = ("rgb", "alpha", "depth", "features")
    graded = _render(scene, _leaves(scene), outputs, op=render, tile_size=8)
    function = FastRasterizeFunction if op == "gaussians" else FastSurfelsFunction
    monkeypatch.setattr(function, "apply", None)  # from here on, entering autograd fails the test
    plain = _render(scene, _leaves(scene, False), outputs, op=render, tile_size=8)
    with torch.no_grad():
        no_grad = _render(scene, _leaves(scene), outputs, op=render, tile_size=8)
    assert graded.rgb.grad_fn is not None
    for out in (plain, no_grad):
        assert out.num_intersections == graded.num_intersections > 0
        assert torch.equal(out.visible, graded.visible)
        for name in outputs:
            assert getattr(out, name).grad_fn is None and not getattr(out, name).requires_grad, name
            _assert_same(getattr(out, name), getattr(graded, name).detach(), name)


@pytest.mark.parametrize("op", ["gaussians", "surfels"])
@pytest.mark.parametrize("leaf", ["features", "K", "background"])
def test_a_render_where_one_input_needs_a_gradient_still_gets_it(op, leaf):
    """run_op skips autograd only when no tensor argument needs a gradient: an input that alone needs one (the
    features, the camera, or the background, which is blended outside the op) still gets it."""
    scene = random_scene(n=60, seed=7, num_features=2)
    if op == "surfels":
        scene = dict(scene, scales=scene["scales"][:, :2])
    render = op_for(op == "surfels")
    leaves = _leaves(scene, False)
    background = torch.full((3,), 0.3, device=DEVICE)
    wanted = {"features": leaves["features"], "K": leaves["K"], "background": background}[leaf].requires_grad_(True)
    out = _render(scene, leaves, ("rgb", "features"), op=render, tile_size=8, background=background)
    (out.rgb.sum() + out.features.sum()).backward()
    assert wanted.grad is not None and wanted.grad.abs().sum() > 0 and torch.isfinite(wanted.grad).all()


def test_interleaved_renders_keep_their_own_buffers():
    """Two forwards, then their backwards in reverse order (and a forward-only render and a render of another
    size in between, which reuse and grow the scratch memory): every gradient equals that of a render
    differentiated on its own."""
    scenes = [random_scene(n=50, seed=s, num_features=2) for s in (11, 12)]
    outputs = ("rgb", "alpha", "depth", "features")
    alone = [_run(s, outputs)[1] for s in scenes]

    leaves = [_leaves(s) for s in scenes]
    outs = [_render(s, lv, outputs) for s, lv in zip(scenes, leaves)]
    with torch.no_grad():  # reuses the workspace a forward-only render gets
        big = random_scene(n=120, seed=13, width=64, height=48)
        _render(big, _leaves(big, False), ("rgb", "alpha"))
    _run(random_scene(n=200, seed=14, width=72, height=40), ("rgb",))  # grows every buffer
    for i in (1, 0):
        _loss(outs[i], _weights(scenes[i], outputs)).backward()
    for i in (0, 1):
        for name, g in alone[i].items():
            _assert_same(leaves[i][name].grad, g, f"scene {i} grad {name}")


def test_growing_and_shrinking_scenes_between_calls():
    """The workspace grows and hands out smaller views again; each render equals the oracle's."""
    for n, (w, h) in [(30, (40, 30)), (120, (64, 48)), (10, (16, 16)), (80, (40, 30))]:
        scene = random_scene(n=n, seed=n, width=w, height=h)
        ref, ref_grads = _run(scene, ("rgb", "alpha"), op=rasterize_legacy)
        out, grads = _run(scene, ("rgb", "alpha"))
        _assert_same(out.rgb.detach(), ref.rgb.detach(), f"rgb n={n}")
        for name, g in ref_grads.items():
            _assert_same(grads[name], g, f"grad {name} n={n}", _exact_grad({}, name))


def test_empty_and_fully_culled_scenes():
    for n, behind in ((0, False), (5, True)):
        scene = random_scene(n=max(n, 1), seed=1)
        scene = {k: (v[:n] if isinstance(v, torch.Tensor) and k not in ("viewmat", "K") else v)
                 for k, v in scene.items()}
        if behind:
            scene["means"] = scene["means"].clone()
            scene["means"][:, 2] = -10.0  # all behind the camera: no tile pairs
        out, grads = _run(scene, ("rgb", "alpha"))
        assert out.num_intersections == 0
        assert torch.all(out.alpha == 0)
        for name, g in grads.items():
            assert torch.all(g == 0), name


def test_batch_of_cameras_on_the_fast_path():
    scene = random_scene(n=40, seed=6)
    lv = _leaves(scene)
    views = torch.stack([lv["viewmat"], look_at((1.0, 0.0, -4.0), (0.0, 0.0, 0.0)).float().to(DEVICE)])
    Ks = torch.stack([lv["K"], lv["K"]])
    ref, out = (op(lv["means"], lv["quats"], lv["scales"], lv["opacities"], lv["colors"], views, Ks, scene["width"],
                   scene["height"], outputs=("rgb", "depth")) for op in (rasterize_legacy, rasterize))
    _assert_same(out.rgb, ref.rgb, "rgb")
    _assert_same(out.depth, ref.depth, "depth")


def test_expanded_and_unused_upstream_gradients():
    """`out.rgb.sum()` hands the backward a broadcast (stride-0) gradient that must be copied to a contiguous one,
    and outputs the loss ignores (alpha here) get zeros: the copies must stay alive while the adjoint reads them.
    The image is large enough that a freed copy is returned to the system (reading it crashed before)."""
    scene = random_scene(n=200, seed=21, width=400, height=300, num_features=2)
    outputs = ("rgb", "alpha", "depth", "features")
    results = []
    for op in (rasterize_legacy, rasterize):
        leaves = _leaves(scene)
        out = _render(scene, leaves, outputs, op=op)
        (out.rgb.sum() + out.depth.sum() + out.features[..., 1].sum()).backward()  # alpha unused
        results.append({k: v.grad for k, v in leaves.items() if v is not None})
    for name, g in results[0].items():
        _assert_same(results[1][name], g, f"grad {name}", _exact_grad({}, name))


def test_outputs_the_loss_never_touches_get_no_gradient_buffers():
    """The fast op asks autograd not to materialise zero gradients: a loss on rgb alone hands its backward None
    for alpha, depth and features, which must count as zeros (the oracle gets real zero tensors)."""
    scene = random_scene(n=80, seed=22, num_features=2)
    results = []
    for op in (rasterize_legacy, rasterize):
        leaves = _leaves(scene)
        out = _render(scene, leaves, ("rgb", "alpha", "depth", "features"), op=op)
        out.rgb.sum().backward()
        results.append({k: v.grad for k, v in leaves.items() if v is not None})
    for name, g in results[0].items():
        _assert_same(results[1][name], g, f"grad {name}", _exact_grad({}, name))


def test_intrinsics_changed_in_place_are_seen():
    """The op remembers each K tensor's (fx, fy, cx, cy) while K stays the same object at the same version; an
    in-place change of K must render as a fresh K does."""
    scene = random_scene(n=60, seed=23)
    leaves = _leaves(scene, requires_grad=False)
    first = _render(scene, leaves, ("rgb",)).rgb
    with torch.no_grad():
        leaves["K"][0, 0] *= 1.5
        leaves["K"][1, 2] += 3.0
    changed = _render(scene, leaves, ("rgb",)).rgb
    fresh = _render(scene, dict(leaves, K=leaves["K"].clone()), ("rgb",)).rgb
    assert not torch.equal(changed, first)
    assert torch.equal(changed, fresh)


@pytest.mark.parametrize("with_alpha", [False, True])
def test_depth_division_kernel_matches_torch(with_alpha):
    """The fast op divides accumulated depth by alpha in the blend kernel as it writes the pixel, and runs that
    division's adjoint itself; the oracle leaves both to torch. Same images and gradients, uncovered pixels (alpha 0) included."""
    scene = random_scene(n=120, seed=24, width=48, height=40)
    results = []
    for op in (rasterize_legacy, rasterize):
        leaves = _leaves(scene)
        out = _render(scene, leaves, ("rgb", "alpha", "depth"), op=op)
        assert bool((out.alpha == 0).any()), "the scene should leave some pixels uncovered"
        weights = _weights(scene, ("depth", "alpha"), seed=7)
        loss = (out.depth * weights["depth"]).sum()
        if with_alpha:
            loss = loss + (out.alpha * weights["alpha"]).sum()
        loss.backward()
        results.append((out.depth.detach(), {k: v.grad for k, v in leaves.items() if v is not None}))
    _assert_same(results[1][0], results[0][0], "depth")
    for name, g in results[0][1].items():
        _assert_same(results[1][1][name], g, f"grad {name}", _exact_grad({}, name))


def test_removed_and_unknown_raster_options_are_named():
    """`path` (the legacy host path) and `sort` (the single 64-bit sort) are gone: asking for them names them."""
    for name in ("path", "sort"):
        with pytest.raises(ValueError, match=f"unknown option.*'{name}'"):
            with raster_options(**{name: "legacy"}):
                pass
    with pytest.raises(ValueError, match="backward_kernel"):
        with raster_options(backward_kernel="fastest"):
            pass


@pytest.mark.parametrize("surfels", [False, True])
def test_a_second_backward_through_a_render_is_refused_by_name(surfels):
    """The render ops give a render's buffers back after its backward (held to the graph's end, a caller keeping
    each step's loss would lease a set a step), so loss.backward(retain_graph=True) twice raises a clear error
    instead of failing inside the op; the first backward's gradients are intact."""
    op, s = op_for(surfels), op_scene()
    leaves = op_leaves(s, surfels)
    out = op(*leaves, s["viewmat"], s["K"], s["width"], s["height"], outputs=("rgb", "depth"))
    loss = out.rgb.sum() + out.depth.sum()
    loss.backward(retain_graph=True)
    assert all(t.grad is not None and torch.isfinite(t.grad).all() for t in leaves)
    with pytest.raises(RuntimeError, match="back-propagated already"):
        loss.backward()


def test_keeping_each_steps_loss_leases_no_more_buffers(monkeypatch):
    """A training loop that keeps every step's loss tensor (graph and all, e.g. a list for logging) must not hold a
    render's buffer set per step: the op gives it back when its backward ends."""
    from warpgs.render import workspace

    s = op_scene()
    leaves = op_leaves(s, surfels=False)
    kept = []

    def step():
        out = rasterize(*leaves, s["viewmat"], s["K"], s["width"], s["height"], outputs=("rgb",))
        loss = out.rgb.sum()
        loss.backward()
        kept.append(loss)

    step()
    made, init = [0], workspace.Buffers.__init__

    def counting(self, *args, **kwargs):
        made[0] += 1
        init(self, *args, **kwargs)

    monkeypatch.setattr(workspace.Buffers, "__init__", counting)
    for _ in range(4):
        step()
    assert made[0] == 0 and len(kept) == 5


@pytest.mark.parametrize("surfels", [False, True])
@pytest.mark.parametrize("loss", ["squared", "linear"])
def test_a_second_derivative_through_a_render_is_refused(surfels, loss):
    """The ops' backward is Warp kernels, differentiable once: a gradient penalty (create_graph=True) must fail
    loudly, not leave the render's part of it out, also for a loss linear in the image (whose incoming gradient is
    a constant: torch's once_differentiable lets that through)."""
    op, s = op_for(surfels), op_scene()
    leaves = op_leaves(s, surfels)
    out = op(*leaves, s["viewmat"], s["K"], s["width"], s["height"], outputs=("rgb",))
    value = ((out.rgb - 0.5) ** 2).sum() if loss == "squared" else out.rgb.mean()
    with pytest.raises(RuntimeError, match="render.*not differentiable"):
        torch.autograd.grad(value, [leaves[0]], create_graph=True)
    (g,) = torch.autograd.grad(op(*leaves, s["viewmat"], s["K"], s["width"], s["height"]).rgb.mean(), [leaves[0]])
    assert torch.isfinite(g).all()  # a first derivative as usual
