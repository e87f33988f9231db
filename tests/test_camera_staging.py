"""The render ops copy each call's camera (viewmat, intrinsics, the checked K and background) into buffers of their
own before the launches up to the sync, so that sequence's key (render/workspace.py) is the same for every view of
a training run and replays from its CUDA graph. The backward must still read the camera of its own call: the
buffers are rewritten by the next render."""
import pytest
import torch

from random_scenes import look_at
from raster_helpers import DEVICE, op_for, op_leaves as _leaves, op_scene as _scene
from warpgs.render import device_state, validation, workspace
from warpgs.render.defaults import raster_options


def _camera(eye):
    return look_at(eye, (0.0, 0.0, 0.0)).float().to(DEVICE)


def _K(s, zoom):
    K = s["K"].clone()
    K[:2, :2] *= zoom
    return K


def _forward(s, leaves, viewmat, K, surfels, background=None):
    out = op_for(surfels)(*leaves, viewmat, K, s["width"], s["height"], outputs=("rgb", "depth"),
                          background=background)
    return out.rgb.sum() + 0.1 * out.depth.sum()


@pytest.mark.parametrize("surfels", [False, True])
def test_the_launch_sequence_key_does_not_change_with_the_camera(monkeypatch, surfels):
    """With the in-pipeline input checks (the GPU's; here on the CPU too), which also read K and the background."""
    monkeypatch.setattr(validation, "PIPELINE_CHECK_DEVICES", {"cpu", "cuda"})
    keys = []
    run = workspace.LaunchSequence.run

    def recording(self):
        values = run(self)  # sets the host buffer the key names (on a GPU; the CPU reads without one)
        if not hasattr(self, "_host"):
            self._host = None
        keys.append(self._key()[0])
        return values

    monkeypatch.setattr(workspace.LaunchSequence, "run", recording)
    # a fresh state: a full descriptor memo (after many other tests) is cleared whole, which can change a key once
    device_state.release_workspaces()
    s = _scene()
    leaves = [t.detach() for t in _leaves(s, surfels)]
    # the exact pair sort: the launches up to the sync are each render's one sequence (the GPU's other pair sorts
    # add a sequence sized by the count, which differs between the views)
    with raster_options(pair_sort="exact"):
        for eye, zoom, grey in (((0.3, -0.2, -4.0), 1.0, 0.2), ((-0.5, 0.1, -3.5), 1.1, 0.6)):
            # a background that wants a gradient while the Gaussians do not: the op runs without autograd
            background = torch.full((3,), grey, device=DEVICE, requires_grad=True)
            _forward(s, leaves, _camera(eye), _K(s, zoom), surfels, background)
    assert len(keys) == 2 and keys[0] == keys[1]
    staged = [buf for buf, _ in device_state.device_state(leaves[0].device)._staged.values()]
    assert staged and all(b.grad_fn is None and not b.requires_grad for b in staged)  # no autograd chain through them


@pytest.mark.parametrize("surfels", [False, True])
def test_interleaved_renders_of_two_cameras_get_their_own_gradients(surfels):
    s = _scene()
    cameras = (((0.3, -0.2, -4.0), 1.0), ((-0.5, 0.1, -3.5), 1.15))  # each its own pose and intrinsics
    alone = []
    for eye, zoom in cameras:
        leaves, view, K = _leaves(s, surfels), _camera(eye).requires_grad_(True), _K(s, zoom).requires_grad_(True)
        _forward(s, leaves, view, K, surfels).backward()
        alone.append([t.grad for t in leaves] + [view.grad, K.grad])
    both = [(_leaves(s, surfels), _camera(eye).requires_grad_(True), _K(s, zoom).requires_grad_(True))
            for eye, zoom in cameras]
    losses = [_forward(s, leaves, view, K, surfels) for leaves, view, K in both]  # both forwards first
    for loss in reversed(losses):  # the first camera's backward runs after the second camera's forward
        loss.backward()
    for (leaves, view, K), expected in zip(both, alone):
        for got, want in zip([t.grad for t in leaves] + [view.grad, K.grad], expected):
            assert torch.allclose(got, want, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("surfels", [False, True])
def test_a_first_render_under_inference_mode_leaves_later_renders_working(surfels):
    device_state.release_workspaces()  # a fresh state for this thread: its buffers are made by the next render
    s = _scene()
    with torch.inference_mode():
        _forward(s, [t.detach() for t in _leaves(s, surfels)], _camera((0.3, -0.2, -4.0)), s["K"], surfels)
    leaves = _leaves(s, surfels)
    _forward(s, leaves, _camera((-0.5, 0.1, -3.5)), s["K"], surfels).backward()
    assert all(t.grad is not None and torch.isfinite(t.grad).all() for t in leaves)
