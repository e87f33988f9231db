"""benchmarks/raster_views.py: renders along a moving camera."""
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import raster_views  # noqa: E402
from random_scenes import random_scene  # noqa: E402


def test_the_path_moves_the_camera_and_only_its_position():
    viewmat = torch.eye(4)
    views = raster_views.camera_path(viewmat, 12)
    assert len(views) == 12 and torch.equal(viewmat, torch.eye(4))  # the given view is left alone
    for a, b in zip(views, views[1:]):
        assert torch.equal(a[:3, :3], b[:3, :3]) and not torch.equal(a[:3, 3], b[:3, 3])
    assert len({tuple(v[:3, 3].tolist()) for v in views}) == 12


def test_each_view_is_rendered_twice_and_timed_once():
    calls = []
    ms = raster_views.ms_per_view(calls.append, [1, 2, 3], "cpu")
    assert calls == [1, 2, 3, 1, 2, 3] and ms >= 0.0


def test_both_modes_render_a_small_scene_on_the_cpu():
    s = random_scene(n=40, width=32, height=24)
    scene = tuple(s[k].float() for k in ("means", "quats", "scales", "opacities", "colors", "viewmat", "K"))
    for backward in (False, True):
        render = raster_views.warpgs_view(scene, 32, 24, backward)
        for v in raster_views.camera_path(scene[5], 3):
            render(v)
    out = raster_views.warpgs_view(scene, 32, 24, False)(scene[5])
    assert out.rgb.shape == (24, 32, 3) and torch.isfinite(out.rgb).all()
