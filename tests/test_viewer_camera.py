"""The viewer's parts that need no viser: browser camera <-> our camera, the frame loop (small frames while the
camera moves, one still frame after) and the lock that lets a viewer thread render between training steps (one
test checks our quaternions against viser's own)."""
import math
import threading
import time

import numpy as np
import pytest
import torch

from warpgs.viewer.camera import ViewerCamera, fit_size, quat_to_matrix, to_warpgs
from warpgs.viewer.frames import FrameLoop, Resolution
from warpgs.viewer.turn_lock import TurnLock

from viewer_fixtures import _as_viewer, _camera, _wait, needs_viser  # noqa: F401


# ----- camera maths (no viser needed) -----------------------------------------------------------------------------
def test_viewer_camera_gives_back_the_camera_it_came_from():
    cam = _camera()
    viewmat, K = to_warpgs(_as_viewer(cam), cam.width, cam.height)
    assert np.allclose(viewmat, cam.viewmat, atol=1e-12)
    assert np.allclose(K, cam.K, atol=1e-9)


def test_downscaled_frame_sees_the_same_rays():
    cam = _as_viewer(_camera(width=1000, height=600, f=700.0))
    w, h = fit_size(cam.width, cam.height, 256)
    assert (w, h) == (256, 154) and fit_size(100, 60, 256) == (100, 60)  # never upscaled
    full_vm, full_K = to_warpgs(cam, cam.width, cam.height)
    small_vm, small_K = to_warpgs(cam, w, h)
    assert np.array_equal(full_vm, small_vm)
    p = np.array([0.7, -0.2, 3.5, 1.0])  # a point in view: same relative image position at both sizes
    uv_full = (full_K @ (full_vm @ p)[:3])[:2] / (full_vm @ p)[2] / [cam.width, cam.height]
    uv_small = (small_K @ (small_vm @ p)[:3])[:2] / (small_vm @ p)[2] / [w, h]
    assert np.allclose(uv_full, uv_small, atol=1e-12)


@pytest.mark.parametrize("bad, match", [
    (dict(fov=0.0), "fov"), (dict(fov=math.pi), "fov"), (dict(c2w=np.diag([1.0, 1.0, -1.0, 1.0])), "rotation"),
    (dict(c2w=np.full((4, 4), np.nan)), "c2w"), (dict(width=0), "size"),
])
def test_bad_viewer_cameras_are_named(bad, match):
    good = dict(c2w=np.eye(4), fov=1.0, width=64, height=48)
    with pytest.raises(ValueError, match=match):
        to_warpgs(ViewerCamera(**{**good, **bad}), 64, 48)


@needs_viser
def test_quaternions_follow_viser():
    import viser.transforms as vt

    rng = np.random.default_rng(0)
    for q in rng.normal(size=(20, 4)):
        q /= np.linalg.norm(q)
        assert np.allclose(quat_to_matrix(q), vt.SO3(q).as_matrix(), atol=1e-12)


# ----- the render loop and the lock (no viser needed) ---------------------------------------------------------------
def _loop(render, resolution, **kw):
    sent = []
    cam = _as_viewer(_camera(width=400, height=300, f=300.0))
    loop = FrameLoop(lambda: cam, render, lambda image, info: sent.append((image.shape, info)), resolution,
                     settle=0.05, **kw)
    return loop, sent


def _blank(cam, side):
    w, h = fit_size(cam.width, cam.height, side)
    return torch.full((h, w, 3), 0.5)


def test_frame_loop_moving_frames_small_then_one_still_frame():
    loop, sent = _loop(_blank, Resolution(64, 200))
    loop.moved()
    assert _wait(lambda: loop.stills == 1)
    time.sleep(0.2)  # nothing more without a move
    loop.stop(timeout=5)
    assert [s for s, _ in sent] == [(48, 64, 3), (150, 200, 3)]
    assert [(i.width, i.height, i.still) for _, i in sent] == [(64, 48, False), (200, 150, True)]


def test_frame_loop_collapses_moves_that_arrive_during_a_render():
    def slow(cam, side):
        time.sleep(0.1)
        return _blank(cam, side)

    loop, sent = _loop(slow, Resolution(64, 200))
    for _ in range(20):
        loop.moved()
        time.sleep(0.01)
    assert _wait(lambda: loop.stills == 1)
    loop.stop(timeout=5)
    assert len(sent) <= 5  # 20 moves in 0.2 s: at most ~3 renders of 0.1 s, then the still one
    assert sent[-1][1].still


def test_frame_loop_redraws_when_the_model_changes_and_survives_a_failed_frame():
    version = [0]
    calls = []

    def render(cam, side):
        calls.append(side)
        if len(calls) == 3:
            raise RuntimeError("boom")
        return _blank(cam, side)

    loop, sent = _loop(render, Resolution(64, 200), version=lambda: version[0], refresh=0.05)
    loop.moved()
    assert _wait(lambda: loop.stills == 1)
    version[0] = 1  # training moved on: one new still frame, which fails
    assert _wait(lambda: loop.errors == 1)
    loop.moved()  # the loop is still alive
    assert _wait(lambda: loop.stills == 2)
    loop.stop(timeout=5)
    assert loop.errors == 1 and len(sent) == 4


def test_turn_lock_serves_a_waiting_thread_before_the_holder_takes_it_again():
    lock, order = TurnLock(), []
    lock.acquire()
    lock.acquire()  # reentrant
    waiter = threading.Thread(target=lambda: (lock.acquire(), order.append("waiter"), lock.release()))
    waiter.start()
    assert _wait(lambda: len(lock._queue) == 1)
    lock.release()
    assert lock.locked()  # still held once
    lock.release()
    lock.acquire()  # the trainer's next step: queued behind the waiter
    order.append("holder")
    lock.release()
    waiter.join(5)
    assert order == ["waiter", "holder"]
    with pytest.raises(RuntimeError, match="not held"):
        lock.release()


