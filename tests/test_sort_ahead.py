"""Renders that sort their tile pairs ahead of their count (raster option pair_sort "ahead", the default;
sort_ahead.AheadSort): the same images, count and gradients as the padded sort when the pairs fit the room, the
same again after a redo when they do not, input errors still raised; deterministic renders never sort ahead.

GPUs run these kernels; on the CPU they run with WARPGS_CPU_COOPERATIVE=1 (test_raster_gpu_kernels_on_cpu.py's
"sort_ahead" variant runs this file so) and tile_binning.SPECULATE_ON_CPU: the per-thread CPU kernels never sort
ahead (their feature images accumulate, so a redo would add twice)."""
import pytest
import torch
import warp as wp

from random_scenes import random_scene
from raster_helpers import DEVICE, fresh_pair_rooms
from warpgs import rasterize, rasterize_surfels
from warpgs.render import validation
from warpgs.render.defaults import raster_options
from warpgs.render.pipeline_gaussians import _cooperative

pytestmark = pytest.mark.skipif(
    not _cooperative(wp.get_device(DEVICE)),
    reason="the GPU kernels' path: run by test_raster_gpu_kernels_on_cpu.py with WARPGS_CPU_COOPERATIVE=1, or on a GPU")

W, H, TILE = 64, 48, 8
OUTPUTS = {"gaussians": ("rgb", "alpha", "depth", "inv_depth", "features"),
           "surfels": ("rgb", "alpha", "depth", "normal", "median_depth", "features")}


@pytest.fixture
def rooms(monkeypatch):
    """A workspace that has seen no count yet, sorting ahead on the CPU too."""
    pair_rooms = fresh_pair_rooms(monkeypatch)
    with raster_options(pair_sort="ahead"):  # the default, whatever WARPGS_PAIR_SORT says
        yield pair_rooms


def _ahead_room(rooms, kind):
    return rooms.room(("footprints" if kind == "gaussians" else "surfel_footprints", W, H, TILE, "ahead"))


def _render(scene, kind, grad=False, check_inputs=True):
    tensors = {k: scene[k].detach().float().to(DEVICE) for k in ("means", "quats", "scales", "opacities", "colors",
                                                                   "features")}
    if kind == "surfels":
        tensors["scales"] = tensors["scales"][:, :2].contiguous()
    if grad:
        tensors = {k: t.requires_grad_(True) for k, t in tensors.items()}
    render = rasterize if kind == "gaussians" else rasterize_surfels
    with torch.set_grad_enabled(grad):
        return render(tensors["means"], tensors["quats"], tensors["scales"], tensors["opacities"], tensors["colors"],
                      scene["viewmat"].float().to(DEVICE), scene["K"].float().to(DEVICE), W, H,
                      sh_degree=scene["sh_degree"], features=tensors["features"], outputs=OUTPUTS[kind],
                      tile_size=TILE, check_inputs=check_inputs)


def _padded(scene, kind):
    with raster_options(pair_sort="padded"):
        return _render(scene, kind)


def _assert_same(out, ref, kind):
    assert out.num_intersections == ref.num_intersections > 0
    assert torch.equal(out.visible, ref.visible)
    for name in OUTPUTS[kind]:
        assert torch.equal(getattr(out, name), getattr(ref, name)), name


@pytest.mark.parametrize("kind", ["gaussians", "surfels"])
def test_a_render_that_fits_its_room_matches_the_padded_sort(rooms, kind):
    scene = random_scene(n=300, width=W, height=H, sh_degree=1, num_features=3, seed=21)
    room = _ahead_room(rooms, kind)
    ref = _padded(scene, kind)
    first = _render(scene, kind)  # no room yet: reads its count first, which sizes the room
    assert room.speculative_calls == 0 and room.capacity >= ref.num_intersections
    _assert_same(first, ref, kind)
    for _ in range(2):
        _assert_same(_render(scene, kind), ref, kind)
    assert room.speculative_calls == 2 and room.overflows == 0


@pytest.mark.parametrize("kind", ["gaussians", "surfels"])
def test_a_render_whose_pairs_overflow_is_sorted_again_and_grows_the_room(rooms, kind):
    scene = random_scene(n=300, width=W, height=H, sh_degree=1, num_features=3, seed=22)
    room = _ahead_room(rooms, kind)
    ref = _padded(scene, kind)
    _render(scene, kind)
    room.capacity = ref.num_intersections // 3  # too small: the queued sort drops pairs, the redo must not
    out = _render(scene, kind)
    assert room.overflows == 1 and room.capacity >= ref.num_intersections
    _assert_same(out, ref, kind)


def test_a_scene_with_no_pairs_renders_nothing_when_sorted_ahead(rooms):
    scene = random_scene(n=40, width=W, height=H, num_features=1, seed=23)
    _render(scene, "gaussians")
    scene["means"] = scene["means"] + torch.tensor([0.0, 0.0, -50.0], dtype=torch.float64)  # all behind the camera
    out = _render(scene, "gaussians")
    assert _ahead_room(rooms, "gaussians").speculative_calls == 1
    assert out.num_intersections == 0 and torch.count_nonzero(out.alpha) == 0


@pytest.mark.parametrize("kind", ["gaussians", "surfels"])
def test_non_finite_input_is_still_named_when_sorted_ahead(rooms, kind, monkeypatch):
    # the checks as GPUs run them: flagged in the pipeline, raised when the count is read (the CPU checks in torch)
    monkeypatch.setattr(validation, "PIPELINE_CHECK_DEVICES", validation.PIPELINE_CHECK_DEVICES | {"cpu"})
    scene = random_scene(n=300, width=W, height=H, num_features=1, seed=24)
    _render(scene, kind)
    scene["opacities"] = scene["opacities"].clone()
    scene["opacities"][7] = float("nan")
    with pytest.raises(ValueError, match="opacities"):
        _render(scene, kind)
    assert _ahead_room(rooms, kind).speculative_calls == 1  # it did sort ahead, and still raised


@pytest.mark.parametrize("kind", ["gaussians", "surfels"])
def test_a_render_a_backward_follows_sorts_ahead_with_the_same_gradients(rooms, kind):
    scene = random_scene(n=300, width=W, height=H, sh_degree=1, num_features=3, seed=25)
    room = _ahead_room(rooms, kind)

    def render_and_grads(overflow=False):
        tensors = {k: scene[k].detach().float().to(DEVICE).requires_grad_(True)
                   for k in ("means", "quats", "scales", "opacities", "colors", "features")}
        if kind == "surfels":
            tensors["scales"] = tensors["scales"].detach()[:, :2].contiguous().requires_grad_(True)
        render = rasterize if kind == "gaussians" else rasterize_surfels
        if overflow:
            room.capacity = max(room.capacity // 3, 1)
        out = render(*(tensors[k] for k in ("means", "quats", "scales", "opacities", "colors")),
                     scene["viewmat"].float().to(DEVICE), scene["K"].float().to(DEVICE), W, H,
                     sh_degree=scene["sh_degree"], features=tensors["features"], outputs=OUTPUTS[kind], tile_size=TILE)
        g = torch.Generator().manual_seed(3)
        sum((getattr(out, o) * torch.randn(getattr(out, o).shape, generator=g).to(DEVICE)).sum()
            for o in OUTPUTS[kind]).backward()
        return out, {k: t.grad for k, t in tensors.items()}

    with raster_options(pair_sort="padded"):
        ref, ref_grads = render_and_grads()
    render_and_grads()  # seeds the room
    for overflow in (False, True):
        out, grads = render_and_grads(overflow)
        _assert_same(out, ref, kind)
        for name, g in ref_grads.items():  # the CPU's atomics add in thread order: to float32 rounding
            assert torch.allclose(g, grads[name], rtol=1e-5, atol=2e-6 * float(g.abs().max())), name
    assert room.speculative_calls == 2 and room.overflows == 1


def test_deterministic_renders_never_sort_ahead(rooms):
    scene = random_scene(n=300, width=W, height=H, num_features=1, seed=26)
    with raster_options(deterministic=True):
        for _ in range(3):
            out = _render(scene, "gaussians", grad=True)
            out.rgb.sum().backward()
            assert out.num_intersections > 0
    assert _ahead_room(rooms, "gaussians").speculative_calls == 0 and _ahead_room(rooms, "gaussians").capacity == 0


def test_a_room_much_larger_than_the_last_count_is_not_sorted_whole(rooms):
    big = random_scene(n=300, width=W, height=H, num_features=1, seed=27)
    small = random_scene(n=300, width=W, height=H, num_features=1, seed=27)
    small["scales"] = small["scales"] * 0.05  # the same Gaussians, each on a tile or two: far fewer pairs
    room = _ahead_room(rooms, "gaussians")
    _render(big, "gaussians")
    _render(small, "gaussians")  # sorted ahead in the big room (its last count was the big one)
    assert room.speculative_calls == 1
    ref = _padded(small, "gaussians")
    assert room.capacity > 2 * ref.num_intersections
    _assert_same(_render(small, "gaussians"), ref, "gaussians")  # reads its count first instead
    assert room.speculative_calls == 1
