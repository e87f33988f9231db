"""Calls the Warp op and the float64 reference on the same scene dict."""
import os

import torch

from random_scenes import random_scene
from reference import render_reference
from warpgs import rasterize, rasterize_surfels

ALL_OUTPUTS = ("rgb", "alpha", "depth", "inv_depth", "features")
# The suite runs on the CPU (CI); WARPGS_TEST_DEVICE=cuda runs the Warp side of it on a GPU instead.
DEVICE = os.environ.get("WARPGS_TEST_DEVICE", "cpu")


def render_ours(scene, outputs, background=None, **kw):
    s = {k: (v.float().to(DEVICE) if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    out = rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], s["viewmat"], s["K"],
                    s["width"], s["height"], sh_degree=s["sh_degree"], features=s["features"],
                    background=None if background is None else background.float().to(DEVICE), outputs=outputs, **kw)
    for name in ALL_OUTPUTS + ("visible",):
        if getattr(out, name) is not None:
            setattr(out, name, getattr(out, name).cpu())
    return out


def render_ref(scene, background=None, **kw):
    return render_reference(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                            scene["viewmat"], scene["K"], scene["width"], scene["height"],
                            sh_degree=scene["sh_degree"], features=scene["features"], background=background, **kw)


def requested(scene):
    return tuple(o for o in ALL_OUTPUTS if o != "features" or scene["features"] is not None)


def assert_same_result(a, b, name, exact=True):
    """Two host paths running the same kernels: bit-equal on the CPU (exact=True), else equal to float rounding."""
    assert a.shape == b.shape, name
    a, b = a.detach().cpu(), b.detach().cpu()
    if a.dtype == torch.bool:
        assert torch.equal(a, b), name
        return
    diff = (a - b).abs().max().item() if a.numel() else 0.0
    if exact and DEVICE == "cpu":
        assert torch.equal(a, b), f"{name}: max diff {diff:.3g}"
    else:
        scale = max(1.0, b.abs().max().item()) if b.numel() else 1.0
        assert torch.allclose(a.double(), b.double(), atol=2e-6 * scale, rtol=1e-4), f"{name}: max diff {diff:.3g}"


def op_for(surfels: bool):
    """rasterize, or rasterize_surfels."""
    return rasterize_surfels if surfels else rasterize


def op_scene(n: int = 64, seed: int = 3) -> dict:
    """A small random scene as float32 tensors on DEVICE, for calling the ops directly."""
    return {k: (v.float().to(DEVICE) if isinstance(v, torch.Tensor) else v)
            for k, v in random_scene(n=n, seed=seed).items()}


def op_leaves(scene: dict, surfels: bool) -> list:
    """Fresh leaves (means, quats, scales, opacities, colors) of `scene` that want gradients; 2D scales for surfels."""
    leaves = [scene[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")]
    if surfels:
        leaves[2] = scene["scales"][:, :2].clone().requires_grad_(True)
    return leaves


def fresh_pair_rooms(monkeypatch):
    """This thread's workspace on DEVICE with new (empty) pair rooms for the test, the CPU speculating and sorting ahead
    too (tile_binning.SPECULATE_ON_CPU); what earlier tests left in flight is settled first."""
    from warpgs.render import tile_binning
    from warpgs.render.device_state import device_state
    from warpgs.render.pair_room import PairRooms

    monkeypatch.setattr(tile_binning, "SPECULATE_ON_CPU", True)
    ws = device_state(torch.device(DEVICE)).ws
    ws.pair_rooms.stats()
    monkeypatch.setattr(ws, "pair_rooms", PairRooms())
    return ws.pair_rooms
