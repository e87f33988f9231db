"""A real browser painting our frame and driving the viewer's camera: Playwright with a Chromium (Debian:
`apt-get install chromium`; or WARPGS_CHROMIUM=/path/to/chrome). Skips with its reason without them or without
the `viewer` extra."""
import math
import os
import shutil
from io import BytesIO

import numpy as np
import pytest
import torch
from PIL import Image

from warpgs.model.gaussians import GaussianModel
from warpgs.viewer.frames import Resolution

from viewer_fixtures import _wait, needs_viser  # noqa: F401


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
