"""The browser viewer (warpgs/viewer): errors that name the option or path, the server (its HTTP page, frames equal
to render_model, run folders and PLYs), the CLI, exit during a frame, and the live viewer leaving training
unchanged. Its camera maths and frame loop: test_viewer_camera.py; a real browser: test_viewer_browser.py.

Tests that start a server need the `viewer` extra (viser) and skip without it.
"""
import shutil
import subprocess
import sys
import threading
import urllib.request

import numpy as np
import pytest
import torch

from train_fixtures import quick_overrides
from warpgs.data.camera import invert_rigid, look_at
from warpgs.model.rendering import render_model
from warpgs.viewer.camera import ViewerCamera
from warpgs.viewer.frames import Resolution
from warpgs.viewer.turn_lock import TurnLock

from viewer_fixtures import ROOT, _as_viewer, _camera, model, needs_viser, ply, run_dir  # noqa: F401 (fixtures)


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
def test_display_modes_show_the_maps_of_the_same_render(viewer, model):
    from warpgs.model.maps import depth_colours

    cam = _camera()
    out = render_model(model, cam.viewmat_tensor(), cam.K_tensor(), cam.width, cam.height,
                       outputs=("depth", "alpha"), background=torch.tensor([0.1, 0.2, 0.3]))
    viewer.set_display("depth")
    depth = viewer.frame(_as_viewer(cam))
    assert torch.equal(depth, depth_colours(out.depth[..., 0], out.alpha[..., 0] >= 0.5))
    assert depth.std() > 0.01
    viewer.set_display("alpha")
    assert torch.equal(viewer.frame(_as_viewer(cam)), out.alpha.expand(-1, -1, 3))
    with pytest.raises(ValueError, match=r"a gaussians model shows one of \['rgb', 'depth', 'alpha'\], not 'normal'"):
        viewer.set_display("normal")
    assert viewer.display == "alpha"


@needs_viser
def test_surfels_display_their_normals(model):
    from warpgs.model.gaussians import SurfelModel
    from warpgs.model.maps import normal_colours
    from warpgs.viewer.server import Viewer
    from warpgs.viewer.sources import ModelSource

    surfels = SurfelModel.from_points(model.means.detach(), torch.rand(model.num_primitives, 3), sh_degree=1)
    v = Viewer(ModelSource(surfels), port=0, resolution=Resolution(64, 128))
    try:
        v.set_display("normal")
        cam = _camera()
        image = v.frame(_as_viewer(cam))
        out = render_model(surfels, cam.viewmat_tensor(), cam.K_tensor(), cam.width, cam.height,
                           outputs=("normal", "alpha"))
        valid = out.alpha[..., 0] >= 0.5
        assert valid.any() and torch.equal(image, normal_colours(out.normal, valid))
    finally:
        v.close()


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
        # Generous: it checks that Ctrl-C ends the viewer, and a loaded 2-core machine once needed over 30 s for
        # the render loop's last frame plus viser's shutdown.
        assert proc.wait(90) == 0
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
    kind = "gaussians"
    def render(self, viewmat, K, width, height, mode="rgb"):
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


