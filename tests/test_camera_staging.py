"""The render ops copy each call's camera (viewmat, intrinsics, the checked K and background) into buffers of their
own before the launches up to the sync, so that sequence's key (render/workspace.py) is the same for every view of
a training run and replays from its CUDA graph. The backward must still read the camera of its own call: the
buffers are rewritten by the next render."""
import pytest
import torch

from random_scenes import look_at, random_scene
from raster_helpers import DEVICE
from warpgs import rasterize, rasterize_surfels
from warpgs.render import workspace

OPS = {"gaussians": rasterize, "surfels": rasterize_surfels}


def _scene():
    s = random_scene(n=64, seed=3)
    return {k: (v.float().to(DEVICE) if isinstance(v, torch.Tensor) else v) for k, v in s.items()}


def _camera(eye):
    return look_at(eye, (0.0, 0.0, 0.0)).float().to(DEVICE)


def _leaves(s, surfels):
    leaves = [s[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")]
    if surfels:
        leaves[2] = s["scales"][:, :2].clone().requires_grad_(True)
    return leaves


def _forward(s, leaves, viewmat, K, surfels):
    out = OPS["surfels" if surfels else "gaussians"](*leaves, viewmat, K, s["width"], s["height"],
                                                     outputs=("rgb", "depth"))
    return out.rgb.sum() + 0.1 * out.depth.sum()


@pytest.mark.parametrize("surfels", [False, True])
def test_the_launch_sequence_key_does_not_change_with_the_camera(monkeypatch, surfels):
    keys = []
    run = workspace.LaunchSequence.run

    def recording(self):
        values = run(self)  # sets the host buffer the key names (on a GPU; the CPU reads without one)
        if not hasattr(self, "_host"):
            self._host = None
        keys.append(self._key()[0])
        return values

    monkeypatch.setattr(workspace.LaunchSequence, "run", recording)
    s = _scene()
    leaves = [t.detach() for t in _leaves(s, surfels)]
    with torch.no_grad():
        for eye in ((0.3, -0.2, -4.0), (-0.5, 0.1, -3.5)):
            _forward(s, leaves, _camera(eye), s["K"].clone(), surfels)
    assert len(keys) == 2 and keys[0] == keys[1]


@pytest.mark.parametrize("surfels", [False, True])
def test_interleaved_renders_of_two_cameras_get_their_own_gradients(surfels):
    s = _scene()
    eyes = ((0.3, -0.2, -4.0), (-0.5, 0.1, -3.5))
    alone = []
    for eye in eyes:
        leaves, view = _leaves(s, surfels), _camera(eye).requires_grad_(True)
        _forward(s, leaves, view, s["K"].clone(), surfels).backward()
        alone.append([t.grad for t in leaves] + [view.grad])
    both = [(_leaves(s, surfels), _camera(eye).requires_grad_(True)) for eye in eyes]
    losses = [_forward(s, leaves, view, s["K"].clone(), surfels) for leaves, view in both]  # both forwards first
    for loss in reversed(losses):  # the first camera's backward runs after the second camera's forward
        loss.backward()
    for (leaves, view), expected in zip(both, alone):
        for got, want in zip([t.grad for t in leaves] + [view.grad], expected):
            assert torch.allclose(got, want, atol=1e-5, rtol=1e-4)
