"""Shared pieces of the viewer tests (tests/test_viewer*.py): an upright camera as a browser has it, its viewer
form, a small model, its PLY, a short training run, and the mark for tests that need the `viewer` extra."""
import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from train_fixtures import quick_overrides
from warpgs.data.camera import Camera, invert_rigid, look_at
from warpgs.model.gaussians import GaussianModel
from warpgs.viewer.camera import ViewerCamera

ROOT = Path(__file__).resolve().parent.parent
try:
    import viser  # noqa: F401
    HAVE_VISER = True
except ImportError:  # not installed, or broken
    HAVE_VISER = False
needs_viser = pytest.mark.skipif(not HAVE_VISER,
                                 reason="the viewer extra is not installed: pip install 'warpgs[viewer]'")


def _camera(width=96, height=64, f=80.0, eye=(0.3, -0.4, -0.5), target=(0.0, 0.0, 3.0)):
    """An upright camera with the principal point at the image centre, as a browser camera has it."""
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return Camera(K, look_at(eye, target, (0.0, -1.0, 0.0)), width, height, name="ref")


def _as_viewer(cam: Camera) -> ViewerCamera:
    return ViewerCamera(invert_rigid(cam.viewmat), 2 * math.atan(cam.height / (2 * cam.fy)), cam.width, cam.height)


@pytest.fixture(scope="module")
def model():
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(400, 3, generator=g) * 0.4 + torch.tensor([0.0, 0.0, 3.0])
    return GaussianModel.from_points(pts, torch.rand(400, 3, generator=g), sh_degree=1)


@pytest.fixture(scope="module")
def ply(model, tmp_path_factory):
    path = tmp_path_factory.mktemp("ply") / "small.ply"
    model.save_ply(path)
    return path


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A short training run's output folder (config.yaml, checkpoint.pt, point_cloud.ply)."""
    from warpgs.train.trainer import Trainer

    out = tmp_path_factory.mktemp("run")
    Trainer(None, overrides=quick_overrides(out, 12), quiet=True).fit()
    return out


def _wait(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.005)
    return cond()
