"""Speculative binning (rasterize / rasterize_surfels(speculative_pairs=True), render/pair_room.py): a render sized
from earlier calls' tile-pair counts gives the exact path's bits when its pairs fit, flags itself when they do not
(and stays finite), and the trainer skips such a step on the device without an error. The path saves a GPU's host
sync; on the CPU it runs here through tile_binning.SPECULATE_ON_CPU, the same kernels."""
import math

import pytest
import torch

from random_scenes import random_scene
from raster_helpers import DEVICE, fresh_pair_rooms
from warpgs import rasterize, rasterize_surfels
from warpgs.losses.registry import LossResult
from warpgs.render import tile_binning
from warpgs.render.device_state import device_state
from warpgs.render.pair_room import MIN_ROOM, SIZES_PER_DOUBLING, PairRoom, PairRooms, room_size
from warpgs.train.guard import NonFiniteError, NonFiniteGuard, StepGuard

LEAVES = ("means", "quats", "scales", "opacities", "colors", "features")
OUTPUTS = ("rgb", "alpha", "depth", "features")


@pytest.fixture
def speculate(monkeypatch):
    """The room of the tests' 64x48 renders at tile 8, in a workspace that has seen no count yet."""
    return fresh_pair_rooms(monkeypatch).room(("footprints", 64, 48, 8))


def _render(scene, speculative, outputs=OUTPUTS, tile=8):
    """A render and its gradients; speculative renders skip the input checks, as the trainer's do (on a GPU the
    checks' flags are read at the pair count's sync, which the speculative path has not)."""
    leaves = {k: scene[k].detach().float().to(DEVICE).requires_grad_(True) for k in LEAVES if scene[k] is not None}
    out = rasterize(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
                    scene["viewmat"].float().to(DEVICE), scene["K"].float().to(DEVICE), scene["width"],
                    scene["height"], sh_degree=scene["sh_degree"], features=leaves.get("features"), outputs=outputs,
                    track_means2d=True, speculative_pairs=speculative, check_inputs=not speculative, tile_size=tile)
    g = torch.Generator().manual_seed(1)
    loss = sum((getattr(out, o) * torch.randn(getattr(out, o).shape, generator=g).to(DEVICE)).sum() for o in outputs)
    loss.backward()
    grads = {k: v.grad for k, v in leaves.items()}
    grads["means2d"] = out.means2d.grad
    return out, grads


def _same(a, b, exact):
    """Bit for bit, or (GPU atomics, whose order changes from run to run) to float32 rounding of the largest
    entry: on an H200 the two paths' gradients differed by at most 1.5e-7 of it."""
    return torch.equal(a, b) if exact else torch.allclose(a, b, rtol=1e-5, atol=2e-6 * float(b.abs().max()))


@pytest.mark.parametrize("tile", [8, 16])
def test_a_render_that_fits_its_room_matches_the_exact_path(speculate, tile):
    scene = random_scene(n=300, width=64, height=48, sh_degree=1, num_features=2, seed=tile)
    room = device_state(torch.device(DEVICE)).ws.pair_rooms.room(("footprints", 64, 48, tile))
    exact, exact_grads = _render(scene, False, tile=tile)
    assert exact.pairs_overflowed is None and exact.num_intersections > 0
    first, _ = _render(scene, True, tile=tile)  # the room's first count: sized exactly, with its sync
    assert first.num_intersections == exact.num_intersections and int(first.pairs_overflowed) == 0
    out, grads = _render(scene, True, tile=tile)
    assert room.speculative_calls == 1 and out.num_intersections == -1
    assert int(out.pairs_overflowed) == 0
    assert room.capacity >= exact.num_intersections
    on_cpu = DEVICE == "cpu"  # GPU atomics sum in another order from run to run
    for name in OUTPUTS:
        assert torch.equal(getattr(out, name), getattr(exact, name)), name
    for name, g in exact_grads.items():
        assert _same(grads[name], g, on_cpu), name


def test_a_render_that_overflows_is_flagged_stays_finite_and_grows_the_room(speculate):
    scene = random_scene(n=300, width=64, height=48, seed=3)
    exact, _ = _render(scene, False, ("rgb", "alpha"))
    _render(scene, True, ("rgb", "alpha"))  # the exact sizing that seeds the room
    speculate.settle()
    speculate.capacity = exact.num_intersections // 3  # too small: some pairs are dropped
    overflows = speculate.overflows
    out, grads = _render(scene, True, ("rgb", "alpha"))
    assert int(out.pairs_overflowed) == 1
    assert all(torch.isfinite(t).all() for t in (out.rgb, out.alpha, *grads.values()))
    assert not torch.equal(out.rgb, exact.rgb)
    again, _ = _render(scene, True, ("rgb", "alpha"))  # settles the overflow first: the room has grown
    assert speculate.overflows == overflows + 1
    assert speculate.capacity >= exact.num_intersections
    assert int(again.pairs_overflowed) == 0 and torch.equal(again.rgb, exact.rgb)


def test_a_scene_with_no_pairs_renders_the_background(speculate):
    scene = random_scene(n=20, width=32, height=24, seed=5)
    _render(scene, True, ("rgb", "alpha"))
    scene["means"] = scene["means"] + torch.tensor([0.0, 0.0, -50.0], dtype=torch.float64)  # all behind the camera
    out, grads = _render(scene, True, ("rgb", "alpha"))
    assert out.num_intersections == -1 and int(out.pairs_overflowed) == 0
    assert torch.count_nonzero(out.alpha) == 0 and torch.count_nonzero(grads["means"]) == 0


SURFEL_OUTPUTS = ("rgb", "alpha", "depth", "normal", "median_depth", "features")


def _render_surfels(scene, speculative, outputs=SURFEL_OUTPUTS):
    """As _render, for surfels (the scene's first two scales)."""
    leaves = {k: scene[k].detach().float().to(DEVICE).requires_grad_(True) for k in LEAVES if scene[k] is not None}
    leaves["scales"] = leaves["scales"].detach()[:, :2].contiguous().requires_grad_(True)
    out = rasterize_surfels(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
                            scene["viewmat"].float().to(DEVICE), scene["K"].float().to(DEVICE), scene["width"],
                            scene["height"], sh_degree=scene["sh_degree"], features=leaves.get("features"),
                            outputs=outputs, speculative_pairs=speculative, check_inputs=not speculative)
    g = torch.Generator().manual_seed(1)
    loss = sum((getattr(out, o) * torch.randn(getattr(out, o).shape, generator=g).to(DEVICE)).sum() for o in outputs)
    loss.backward()
    return out, {k: v.grad for k, v in leaves.items()}


def test_a_surfel_render_that_fits_its_room_matches_the_exact_path(speculate):
    scene = random_scene(n=300, width=64, height=48, sh_degree=1, num_features=2, seed=11)
    room = device_state(torch.device(DEVICE)).ws.pair_rooms.room(("surfel_footprints", 64, 48, 8))
    exact, exact_grads = _render_surfels(scene, False)
    assert exact.pairs_overflowed is None and exact.num_intersections > 0
    first, _ = _render_surfels(scene, True)  # the room's first count: sized exactly, with its sync
    assert first.num_intersections == exact.num_intersections and int(first.pairs_overflowed) == 0
    out, grads = _render_surfels(scene, True)
    assert room.speculative_calls == 1 and out.num_intersections == -1 and int(out.pairs_overflowed) == 0
    assert speculate.speculative_calls == 0  # the 3D Gaussians' room of the same size is another
    for name in SURFEL_OUTPUTS:
        assert torch.equal(getattr(out, name), getattr(exact, name)), name
    for name, g in exact_grads.items():
        assert _same(grads[name], g, DEVICE == "cpu"), name


def test_a_surfel_render_that_overflows_is_flagged_and_stays_finite(speculate):
    scene = random_scene(n=300, width=64, height=48, seed=12)
    room = device_state(torch.device(DEVICE)).ws.pair_rooms.room(("surfel_footprints", 64, 48, 8))
    exact, _ = _render_surfels(scene, False, ("rgb", "alpha", "depth"))
    _render_surfels(scene, True, ("rgb", "alpha", "depth"))
    room.settle()
    room.capacity = exact.num_intersections // 3
    out, grads = _render_surfels(scene, True, ("rgb", "alpha", "depth"))
    assert int(out.pairs_overflowed) == 1
    assert all(torch.isfinite(t).all() for t in (out.rgb, out.alpha, out.depth, *grads.values()))
    again, _ = _render_surfels(scene, True, ("rgb", "alpha", "depth"))
    assert room.overflows == 1 and int(again.pairs_overflowed) == 0 and torch.equal(again.rgb, exact.rgb)


@pytest.mark.parametrize("kind", ["gaussians", "surfels"])
def test_a_deterministic_render_asked_to_speculate_sizes_exactly_and_flags_nothing(speculate, kind):
    scene = random_scene(n=300, width=64, height=48, seed=13)
    render = _render if kind == "gaussians" else _render_surfels
    render(scene, True, ("rgb", "alpha"))  # seeds the room: the next call could speculate
    from warpgs.render.defaults import raster_options
    with raster_options(deterministic=True):
        for _ in range(3):
            out, _ = render(scene, True, ("rgb", "alpha"))
            assert out.num_intersections > 0 and int(out.pairs_overflowed) == 0


def test_room_sizes_hold_what_is_asked_and_change_seldom():
    sizes = [room_size(x) for x in range(1, 200000, 997)]
    assert all(s >= max(x, MIN_ROOM) for s, x in zip(sizes, range(1, 200000, 997)))
    assert all(s <= 1.1 * max(x, MIN_ROOM) + 1 for s, x in zip(sizes, range(1, 200000, 997)))
    doublings = math.log2(200000 / MIN_ROOM)
    assert len(set(sizes)) <= SIZES_PER_DOUBLING * doublings + 1  # a few sizes per doubling: few graphs
    room = PairRoom()
    for total in (5000, 9000, 7000):
        room.observe(total)
    assert room.capacity == room_size(9000 * 1.3)  # the recent largest with headroom


def test_the_trainer_skips_a_step_whose_render_overflowed_without_an_error():
    w = torch.nn.Parameter(torch.ones(3))
    opt = torch.optim.Adam([w], lr=0.1, fused=True)
    step_guard = StepGuard(NonFiniteGuard(lambda: [("w", w)]))
    ok = LossResult(torch.tensor(1.0), {"l1": torch.tensor(1.0)}, {"l1": 1.0})
    w.grad = torch.ones(3)
    step_guard.before_optimizers(0, ok, [opt], defer=True, dropped=[torch.tensor(1, dtype=torch.int32)])
    opt.step()
    step_guard.after_optimizers([opt])
    assert torch.equal(w.detach(), torch.ones(3)) and opt.state[w]["step"].item() == 0  # skipped on the device
    w.grad = torch.ones(3)
    step_guard.before_optimizers(1, ok, [opt], defer=True, dropped=[torch.tensor(0, dtype=torch.int32)])  # no error
    opt.step()
    step_guard.after_optimizers([opt])
    assert torch.allclose(w.detach(), torch.full((3,), 0.9))
    w.grad = torch.tensor([1.0, float("nan"), 1.0])  # a non-finite step still raises, with its own step
    step_guard.before_optimizers(2, ok, [opt], defer=True, dropped=[torch.tensor(0, dtype=torch.int32)])
    with pytest.raises(NonFiniteError, match="step 2"):
        step_guard.settle()


def test_without_a_deferred_check_an_overflowed_step_is_dropped_at_once():
    w = torch.nn.Parameter(torch.ones(2))
    opt = torch.optim.Adam([w], lr=0.1, foreach=True)  # cannot skip on the device
    step_guard = StepGuard(NonFiniteGuard(lambda: [("w", w)]))
    w.grad = torch.ones(2)
    step_guard.before_optimizers(0, None, [opt], defer=True, dropped=[torch.tensor(1, dtype=torch.int32)])
    assert w.grad is None
    opt.step()
    assert torch.equal(w.detach(), torch.ones(2))


@pytest.mark.parametrize("kind", ["gaussians", "surfels"])
def test_a_training_run_through_the_speculative_path_skips_only_its_overflowed_step(monkeypatch, tmp_path, kind):
    from warpgs.config.loader import load_config
    from warpgs.train import loop, step
    from warpgs.train.trainer import Trainer

    monkeypatch.setattr(tile_binning, "SPECULATE_ON_CPU", True)
    monkeypatch.setattr(step, "speculative_pairs", lambda trainer: True)  # the GPU's rule, on the CPU
    cfg = load_config(None, ["steps=5", "train.device=cpu", "eval.every=0", "optim.adam_kernel=fused",
                             "data.width=32", "data.height=24", f"output.dir={tmp_path}", "train.progress=false",
                             f"model.kind={kind}"])
    trainer = Trainer(cfg, quiet=True)
    rooms = PairRooms()
    monkeypatch.setattr(device_state(trainer.device).ws, "pair_rooms", rooms)
    trainer.train_step()  # sized exactly: seeds the room
    (room,) = rooms.rooms.values()
    trainer.train_step()
    assert room.speculative_calls == 1
    room.settle()
    room.capacity = room.recent[-1] // 4  # the next render cannot fit
    before = {n: p.detach().clone() for n, p in trainer.named_parameters()}
    trainer.train_step()
    trainer.step_guard.settle()  # no error for it
    assert all(torch.equal(before[n], p.detach()) for n, p in trainer.named_parameters())  # skipped on the device
    trainer.train_step()  # the room has grown: this one applies
    assert room.overflows == 1 and room.speculative_calls == 3
    assert any(not torch.equal(before[n], p.detach()) for n, p in trainer.named_parameters())
    assert loop.speculative_pair_stats(trainer) == {"renders": 3, "skipped": 1}


@pytest.mark.parametrize("change,expected", [({}, True), ({"speculative_pairs": False}, False),
                                             ({"nan_guard": False}, False), ({"deterministic": True}, False),
                                             ({"device": "cpu"}, False), ({"kind": "surfels"}, True),
                                             ({"ranks": True}, False), ({"fused": False}, False)])
def test_the_trainer_speculates_only_where_a_step_can_be_skipped_on_the_device(change, expected):
    from types import SimpleNamespace

    from warpgs.train import step

    o = {"speculative_pairs": True, "nan_guard": True, "deterministic": False, "device": "cuda",
         "kind": "gaussians", "ranks": False, "fused": True, **change}
    w = torch.nn.Parameter(torch.ones(1))
    opt = torch.optim.Adam([w], fused=o["fused"], foreach=None if o["fused"] else True)
    trainer = SimpleNamespace(
        config=SimpleNamespace(train=SimpleNamespace(speculative_pairs=o["speculative_pairs"], nan_guard=o["nan_guard"],
                                                     deterministic=o["deterministic"])),
        device=torch.device(o["device"]), model=SimpleNamespace(kind=o["kind"]),
        ranks=SimpleNamespace(enabled=o["ranks"]), step_guard=StepGuard(NonFiniteGuard(lambda: [])), optimizers=[opt])
    assert step.speculative_pairs(trainer) is expected


def test_each_image_size_has_its_own_room(speculate):
    """Counts scale with the pixels: the first render at a new size is sized exactly, not squeezed into the room of
    a smaller image (a resolution schedule would otherwise skip a step at each change)."""
    small = random_scene(n=300, width=16, height=12, seed=7)
    large = random_scene(n=300, width=64, height=48, seed=7)
    for _ in range(2):
        _render(small, True, ("rgb", "alpha"))
    out, _ = _render(large, True, ("rgb", "alpha"))
    assert out.num_intersections > 0 and int(out.pairs_overflowed) == 0  # exact: this size's first count
    rooms = device_state(torch.device(DEVICE)).ws.pair_rooms
    assert rooms.stats() == {"speculative_calls": 1, "overflows": 0}
    assert speculate is rooms.room(("footprints", 64, 48, 8)) and speculate.capacity >= out.num_intersections


def test_a_batch_of_views_skips_the_step_when_any_view_overflowed(monkeypatch, tmp_path):
    from warpgs.config.loader import load_config
    from warpgs.train import step
    from warpgs.train.trainer import Trainer

    monkeypatch.setattr(tile_binning, "SPECULATE_ON_CPU", True)
    monkeypatch.setattr(step, "speculative_pairs", lambda trainer: True)
    cfg = load_config(None, ["steps=4", "train.device=cpu", "eval.every=0", "optim.adam_kernel=fused",
                             "train.batch_size=2", "data.width=32", "data.height=24", f"output.dir={tmp_path}",
                             "train.progress=false"])
    trainer = Trainer(cfg, quiet=True)
    rooms = PairRooms()
    monkeypatch.setattr(device_state(trainer.device).ws, "pair_rooms", rooms)
    trainer.train_step()  # the first view sizes exactly, the second speculates
    (room,) = rooms.rooms.values()
    room.settle()
    room.capacity = min(room.recent) // 4  # the next step's first view overflows; its second, sized after, fits
    before = {n: p.detach().clone() for n, p in trainer.named_parameters()}
    trainer.train_step()
    trainer.step_guard.settle()
    assert room.stats()["overflows"] == 1  # one view of two: the whole step is skipped
    assert all(torch.equal(before[n], p.detach()) for n, p in trainer.named_parameters())
