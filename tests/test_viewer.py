"""The browser viewer (warpgs/viewer): camera conversion, frames equal to render_model, the HTTP page, errors, the
live viewer leaving training unchanged, and a real browser painting our frame.

Tests that start a server need the `viewer` extra (viser) and skip without it; the browser test also needs
Playwright and a Chromium (Debian: `apt-get install chromium`; or WARPGS_CHROMIUM=/path/to/chrome) and skips
without them.
"""
import math
import os
import shutil
import subprocess
import sys
import threading
import time
import urllib.request
from io import BytesIO
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from train_fixtures import quick_overrides
from warpgs.data.camera import Camera, invert_rigid, look_at
from warpgs.model.gaussians import GaussianModel
from warpgs.model.rendering import render_model
from warpgs.viewer.camera import ViewerCamera, fit_size, quat_to_matrix, to_warpgs
from warpgs.viewer.frames import FrameLoop, Resolution
from warpgs.viewer.turn_lock import TurnLock

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


def _wait(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.005)
    return cond()


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


# ----- errors -----------------------------------------------------------------------------------------------------
def test_missing_extra_names_the_install_command(monkeypatch, capsys, ply):
    from warpgs.viewer.cli import main
    from warpgs.viewer.deps import ViewerUnavailable, require_viser

    monkeypatch.setitem(sys.modules, "viser", None)  # as if not installed
    with pytest.raises(ViewerUnavailable, match=r"pip install 'warpgs\[viewer\]'"):
        require_viser()
    assert main(["--model", str(ply), "--device", "cpu"]) == 2
    assert "warpgs-view needs the viewer extra: pip install 'warpgs[viewer]'" in capsys.readouterr().err


@pytest.mark.parametrize("make, match", [
    (lambda d: d / "missing", "does not exist"),
    (lambda d: (d / "notes.txt").write_text("x") and d / "notes.txt", "is not a .ply file"),
    (lambda d: (d / "empty").mkdir() or d / "empty", "holds none of config.yaml"),
])
def test_bad_model_paths_are_named(tmp_path, capsys, make, match):
    from warpgs.viewer.cli import main

    path = make(tmp_path)
    assert main(["--model", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"warpgs-view: error: --model: {path}" in err and match in err


def test_bad_options_are_named(capsys, ply):
    from warpgs.viewer.cli import main

    assert main(["--model", str(ply), "--background", "pink"]) == 2
    assert "--background: expected black, white or R,G,B" in capsys.readouterr().err
    assert main(["--model", str(ply), "--port", "70000"]) == 2
    assert "--port: expected 0..65535" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert main(["--model", str(ply), "--device", "cuda"]) == 2
        assert "CUDA is not available" in capsys.readouterr().err


def test_a_broken_ply_is_named(tmp_path):
    from warpgs.viewer.load import load_source

    bad = tmp_path / "broken.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(ValueError, match=str(bad)):
        load_source(bad, "cpu")


# ----- the server -------------------------------------------------------------------------------------------------
@pytest.fixture
def viewer(model):
    from warpgs.viewer.server import Viewer
    from warpgs.viewer.sources import ModelSource

    v = Viewer(ModelSource(model, background=(0.1, 0.2, 0.3)), port=0, resolution=Resolution(64, 128))
    yield v
    v.close()


@needs_viser
def test_server_serves_its_page_on_a_free_port(viewer):
    assert viewer.port > 0 and viewer.url == f"http://127.0.0.1:{viewer.port}"
    with urllib.request.urlopen(viewer.url, timeout=10) as r:
        assert r.status == 200
        page = r.read().decode("utf-8", "replace")
    assert "<html" in page.lower() and "viser" in page.lower()


@needs_viser
def test_frame_is_render_model_on_the_same_camera_exactly(viewer, model):
    cam = _camera()
    image = viewer.frame(_as_viewer(cam))
    expected = render_model(model, cam.viewmat_tensor(), cam.K_tensor(), cam.width, cam.height,
                            background=torch.tensor([0.1, 0.2, 0.3])).rgb
    assert image.shape == (cam.height, cam.width, 3)
    assert image.std() > 0.01  # the model is in view, not a blank frame
    assert torch.equal(image, expected)
    small = viewer.frame(_as_viewer(cam), max_side=48)  # the moving frame: same camera, fewer pixels
    assert small.shape == (32, 48, 3)


@needs_viser
def test_run_folder_starts_at_its_first_training_camera(run_dir):
    from warpgs.viewer.load import load_source
    from warpgs.viewer.server import Viewer
    from warpgs.viewer.sources import TrainerSource

    source = load_source(run_dir, "cpu")
    assert isinstance(source, TrainerSource) and source.cameras
    trainer, first = source.trainer, source.cameras[0]
    assert not trainer.config.train.viewer  # a loaded run never starts a viewer of its own
    v = Viewer(source, port=0)
    try:
        start = v.server.initial_camera
        assert np.allclose(start.position, first.center, atol=1e-6)
        # The browser builds its camera from position, look-at and up: that camera renders the training view.
        c2w = invert_rigid(look_at(start.position, start.look_at, start.up))
        image = v.frame(ViewerCamera(c2w, start.fov, first.width, first.height))
        with torch.no_grad():
            expected = trainer.render(trainer.view(trainer.train_indices[0]), ("rgb",)).rgb
        assert torch.allclose(image, expected, atol=1e-4)
    finally:
        v.close()


@needs_viser
def test_run_whose_scene_is_gone_shows_its_ply(run_dir, tmp_path, capsys):
    import yaml

    from warpgs.viewer.load import load_source
    from warpgs.viewer.sources import ModelSource

    moved = tmp_path / "moved"
    shutil.copytree(run_dir, moved)
    cfg = yaml.safe_load((moved / "config.yaml").read_text())
    cfg["data"]["path"] = str(tmp_path / "no-such-scene")
    (moved / "config.yaml").write_text(yaml.safe_dump(cfg))
    source = load_source(moved, "cpu")
    assert isinstance(source, ModelSource) and not source.cameras
    assert "showing point_cloud.ply without its training cameras" in capsys.readouterr().err


@needs_viser
def test_cli_serves_a_ply_until_ctrl_c(ply):
    proc = subprocess.Popen([sys.executable, "-m", "warpgs.viewer", "--model", str(ply), "--port", "0",
                             "--device", "cpu"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT)
    try:
        lines = []  # "warpgs-view: 400 gaussians on cpu; open http://127.0.0.1:PORT (...)", maybe after Warp's
        while not lines or "open http://127.0.0.1:" not in lines[-1]:
            lines.append(proc.stdout.readline())
            assert lines[-1] or proc.poll() is None, "".join(lines) + proc.stderr.read()
            assert len(lines) < 20, "".join(lines)
        line = lines[-1]
        url = line.split("open ", 1)[1].split()[0]
        with urllib.request.urlopen(url, timeout=10) as r:
            assert r.status == 200
        proc.send_signal(2)  # Ctrl-C
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


EXIT_SCRIPT = """
import sys, time, types
import numpy as np, torch
from warpgs.viewer.frames import Resolution
from warpgs.viewer.server import Viewer

class Slow:  # a source whose frame takes a while, as a large one does on the CPU
    device, cameras = torch.device("cpu"), []
    def render(self, viewmat, K, width, height):
        print("frame started", flush=True)
        time.sleep(1.0)
        print("frame finished", flush=True)
        return torch.zeros(height, width, 3)
    def means(self): return np.zeros((1, 3))
    def version(self): return 0
    def status(self): return "slow"

v = Viewer(Slow(), port=0, resolution=Resolution(64, 64))
camera = types.SimpleNamespace(wxyz=np.array([1.0, 0, 0, 0]), position=np.zeros(3), fov=1.0, image_width=64,
                               image_height=48, on_update=lambda cb: None)
v._connect(types.SimpleNamespace(client_id=1, camera=camera,  # a browser, as viser hands it over
                                 scene=types.SimpleNamespace(set_background_image=lambda *a, **k: None)))
time.sleep(0.3)
sys.exit(0)  # mid-frame: the frame must finish before the interpreter goes down
"""


@needs_viser
def test_exit_waits_for_the_frame_in_flight():
    # A render thread still inside torch or Warp when the interpreter shuts down aborts the process (seen: SIGABRT,
    # "terminate called without an active exception", when warpgs-train ended with a browser open).
    proc = subprocess.run([sys.executable, "-c", EXIT_SCRIPT], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "frame started" in proc.stdout and "frame finished" in proc.stdout, proc.stdout


# ----- live during training ---------------------------------------------------------------------------------------
@needs_viser
def test_live_viewer_renders_between_steps_and_leaves_training_unchanged(tmp_path):
    from warpgs.train.trainer import Trainer

    steps = 30  # densification at 10, 20; SH degree raised at 15
    seen = []  # the step each viewer frame was drawn at

    def hammer(trainer):
        cam = _as_viewer(trainer.scene.camera(trainer.train_indices[0]))
        while trainer.step < steps:
            image = trainer.viewer.frame(cam, max_side=32)
            assert torch.isfinite(image).all()
            seen.append(trainer.step)

    def start_hammer(trainer, step, info):  # the same callback in both runs, so only the viewer differs
        if step == 0 and trainer.viewer is not None:
            threading.Thread(target=hammer, args=(trainer,), daemon=True).start()

    def run(out, viewer):
        extra = {"train.viewer": viewer, "train.viewer_port": 0}
        trainer = Trainer(None, overrides=quick_overrides(out, steps, **extra), callbacks=[start_hammer],
                          quiet=True)
        result = trainer.fit()
        return trainer, result

    plain, plain_result = run(tmp_path / "plain", False)
    live, live_result = run(tmp_path / "live", True)
    try:
        assert plain.viewer is None and live.viewer is not None
        assert isinstance(live.lock, TurnLock)
        with urllib.request.urlopen(live.viewer.url, timeout=10) as r:
            assert r.status == 200
    finally:
        live.viewer.close()
    # Frames were drawn while training ran, between most steps: a waiting frame gets the next turn (TurnLock; a
    # plain lock let the training thread take it again first, here 15 to 27 of 30 steps had a frame after them).
    assert len(set(s for s in seen if s < steps)) >= 2 * steps // 3, seen
    assert live_result.loss == plain_result.loss
    assert live_result.num_primitives == plain_result.num_primitives
    for (name, a), (_, b) in zip(plain.named_parameters(), live.named_parameters()):
        assert torch.equal(a.detach(), b.detach()), name


# ----- a real browser ---------------------------------------------------------------------------------------------
def _chromium():
    """A Chromium for Playwright: WARPGS_CHROMIUM, else the system's (None: Playwright's own download, if any)."""
    env = os.environ.get("WARPGS_CHROMIUM")
    if env:
        if not os.path.exists(env):
            pytest.skip(f"no browser test: WARPGS_CHROMIUM={env} does not exist")
        return env
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


@needs_viser
def test_browser_paints_our_frame_and_drives_the_camera():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("no browser test: Playwright is not installed (pip install playwright)")
    from warpgs.viewer.server import Viewer
    from warpgs.viewer.sources import ModelSource

    # One large opaque red Gaussian in front of a blue background: the browser must show red in the middle.
    sh0 = (torch.tensor([1.0, 0.0, 0.0]) - 0.5) / 0.28209479177387814  # colour = 0.5 + C0 * sh0
    red = GaussianModel(torch.zeros(1, 3), torch.full((1, 3), math.log(0.4)), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
                        torch.tensor([8.0]), sh0.reshape(1, 1, 3), torch.zeros(1, 0, 3))
    v = Viewer(ModelSource(red, background=(0.0, 0.0, 1.0)), port=0, resolution=Resolution(64, 256))
    try:
        with sync_playwright() as p:
            exe = _chromium()
            bundled = p.chromium.executable_path
            if exe is None and not os.path.exists(bundled):
                pytest.skip("no browser test: no Chromium found (Debian: apt-get install chromium; "
                            "or set WARPGS_CHROMIUM)")
            browser = p.chromium.launch(executable_path=exe,
                                        args=["--no-sandbox", "--use-angle=swiftshader",
                                              "--enable-unsafe-swiftshader"])
            try:
                page = browser.new_page(viewport={"width": 640, "height": 480})
                page.goto(v.url)
                assert v.wait_for_frames(1, 60), "the server never sent a frame"
                # No training cameras: the browser's camera goes to the pose looking at the model's centre.
                (client,) = v.server.get_clients().values()
                start = v.server.initial_camera
                assert _wait(lambda: np.allclose(client.camera.position, start.position, atol=1e-4), 30)
                assert np.allclose(client.camera.look_at, [0.0, 0.0, 0.0], atol=1e-4)
                assert _wait(lambda: any(loop.stills for loop in v._loops.values()), 30)
                # The frame arrives over the websocket and is drawn in the WebGL canvas: wait until it shows.
                def mean_rgb(x, y, size):
                    shot = page.screenshot(clip={"x": x, "y": y, "width": size, "height": size})
                    return np.asarray(Image.open(BytesIO(shot)).convert("RGB"), dtype=float).mean((0, 1))

                assert _wait(lambda: mean_rgb(300, 220, 40)[0] > 180 and mean_rgb(300, 220, 40)[2] < 80, 30), \
                    mean_rgb(300, 220, 40)
                edge = mean_rgb(5, 200, 20)  # left of the splat: our blue background
                assert edge[2] > 180 and edge[0] < 80, edge
                # Drag the camera: the browser sends its new camera and gets new frames back.
                before = v.frames_sent
                page.mouse.move(320, 240)
                page.mouse.down()
                page.mouse.move(200, 240, steps=10)
                page.mouse.up()
                assert v.wait_for_frames(before + 2, 60), "no frame after the camera moved"
            finally:
                browser.close()
    finally:
        v.close()
