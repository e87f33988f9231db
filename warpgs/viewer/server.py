"""The viewer's web server (viser): each browser gets a FrameLoop that renders its camera through a source.

viser serves a three.js page and streams the browser's camera back; every frame we render is sent as the scene's
background image (JPEG), so what the browser shows is exactly warpgs's render of that camera. The panel: the
model's status, what to display (colour, or depth / normals / alpha as colours), the two resolutions, and a list
of training views to jump to.
"""
from __future__ import annotations

import atexit
import contextlib
import io
import threading
from typing import Dict, Optional

import numpy as np
import torch

from warpgs.viewer.camera import ViewerCamera, fit_size, pose_around, pose_of_camera, scene_up, to_warpgs
from warpgs.viewer.deps import require_viser
from warpgs.viewer.frames import FrameInfo, FrameLoop, Resolution
from warpgs.viewer.sources import display_modes

# Longest image side (pixels) while the camera moves and once it stops. Measured on the 2-core CPU (busy with other
# jobs): 200k random Gaussians 0.4 s at 64x40, 1.0 s at 256x160, 2.7 s at 640x400; 50k: 0.3, 0.7, 2.7 s. A frame
# cannot be cut short, so a large still frame on the CPU delays the next move by as long as it takes.
DEFAULT_RES = {"cpu": (256, 640), "cuda": (1024, 2048)}


def default_resolution(device) -> Resolution:
    moving, still = DEFAULT_RES["cpu" if torch.device(device).type == "cpu" else "cuda"]
    return Resolution(moving, still)


class Viewer:
    """Serves `source` (viewer/sources.py) at http://host:port (port 0: any free one; a busy port moves on to the
    next free one, so read `viewer.port`). `close()` stops the server and the render threads."""

    def __init__(self, source, *, host: str = "127.0.0.1", port: int = 8080,
                 resolution: Optional[Resolution] = None, settle: float = 0.25, refresh: float = 1.0,
                 who: str = "the viewer"):
        viser = require_viser(who)
        if not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"port: expected 0..65535 (0: any free port), got {port!r}")
        self.source = source
        self.resolution = resolution or default_resolution(source.device)
        for name, side in (("moving", self.resolution.moving), ("still", self.resolution.still)):
            if side < 16:
                raise ValueError(f"resolution.{name}: expected at least 16 pixels, got {side}")
        self.settle, self.refresh = settle, refresh
        self.display = "rgb"  # what every browser is shown: a mode of display_modes(source.kind)
        self.host = host
        self._loops: Dict[int, FrameLoop] = {}
        self._closed = False
        self._cond = threading.Condition()
        self.frames_sent = 0
        self._cameras = list(source.cameras)
        self._means = source.means()
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: we print the URL our way
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        try:
            # No share button: it would publish the model through a third-party tunnel.
            self.server.gui.configure_theme(dark_mode=True, show_share_button=False)
            self._setup_scene()
            self._setup_panel()
        except Exception:
            self.server.stop()
            raise
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        atexit.register(self.close)  # after viser's own, so it runs first

    @property
    def url(self) -> str:
        host = "localhost" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{host}:{self.port}"

    # ----- rendering ------------------------------------------------------------------------------------------
    def frame(self, camera: ViewerCamera, max_side: Optional[int] = None) -> torch.Tensor:
        """The [H, W, 3] float image of a browser camera, its canvas scaled down to max_side (None: full size)."""
        width, height = fit_size(camera.width, camera.height, max_side)
        viewmat, K = to_warpgs(camera, width, height)
        return self.source.render(viewmat, K, width, height, mode=self.display)

    def set_display(self, mode: str) -> None:
        """Show `mode` (rgb, depth, normal, alpha; what the source's kind renders) in every browser."""
        modes = display_modes(self.source.kind)
        if mode not in modes:
            raise ValueError(f"display: a {self.source.kind} model shows one of {modes}, not {mode!r}")
        self.display = mode
        self._redraw()

    def wait_for_frames(self, n: int, timeout: float) -> bool:
        """Block until at least n frames went out to browsers (tests; False on timeout)."""
        with self._cond:
            return self._cond.wait_for(lambda: self.frames_sent >= n, timeout)

    def close(self) -> None:
        """Stop the render threads, waiting for a frame in flight (a thread still inside torch when the interpreter
        shuts down aborts the process), then the server. Also runs at exit."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        for loop in list(self._loops.values()):
            loop.stop(timeout=10)
        self.server.stop()

    # ----- scene and panel ------------------------------------------------------------------------------------
    def _setup_scene(self) -> None:
        cams = self._cameras
        pose = pose_of_camera(cams[0], self._means) if cams else pose_around(self._means)
        up = scene_up(cams)
        self.server.scene.set_up_direction(tuple(float(v) for v in (up if up is not None else pose.up)))
        start = self.server.initial_camera
        start.fov = pose.fov
        start.position = tuple(float(v) for v in pose.position)
        start.look_at = tuple(float(v) for v in pose.look_at)
        start.up = tuple(float(v) for v in pose.up)

    def _setup_panel(self) -> None:
        gui = self.server.gui
        self._status = gui.add_markdown(self.source.status())
        modes = display_modes(self.source.kind)
        display = gui.add_dropdown("Display", options=modes, initial_value=self.display,
                                   hint="colour, or depth / normals / alpha as colours (invalid pixels black)")

        @display.on_update
        def _(_):
            self.set_display(display.value)

        moving = gui.add_slider("Moving res", min=64, max=2048, step=32, initial_value=self.resolution.moving,
                                hint="longest image side while the camera moves")
        still = gui.add_slider("Still res", min=64, max=4096, step=32, initial_value=self.resolution.still,
                               hint="longest image side once the camera stops")

        @moving.on_update
        def _(_):
            self.resolution.moving = int(moving.value)
            self._redraw()

        @still.on_update
        def _(_):
            self.resolution.still = int(still.value)
            self._redraw()

        if self._cameras:
            names = [f"{i}: {c.name or 'camera'}" for i, c in enumerate(self._cameras)]
            views = gui.add_dropdown("Training view", options=names, initial_value=names[0],
                                     hint="move this browser's camera to a training camera")

            @views.on_update
            def _(event):
                if event.client is not None:
                    self._go_to(event.client, self._cameras[names.index(views.value)])

    def _go_to(self, client, cam) -> None:
        pose = pose_of_camera(cam, self._means)
        with client.atomic():
            client.camera.fov = pose.fov
            client.camera.position = tuple(float(v) for v in pose.position)
            client.camera.look_at = tuple(float(v) for v in pose.look_at)
            client.camera.up_direction = tuple(float(v) for v in pose.up)

    def _redraw(self) -> None:
        for loop in list(self._loops.values()):
            loop.moved()

    # ----- clients --------------------------------------------------------------------------------------------
    def _connect(self, client) -> None:
        if self._closed:
            return
        def camera() -> ViewerCamera:
            c = client.camera
            return ViewerCamera.from_wxyz(c.wxyz, c.position, c.fov, c.image_width, c.image_height)

        loop = FrameLoop(camera, self.frame, lambda image, info: self._send(client, image, info), self.resolution,
                         version=self.source.version, settle=self.settle, refresh=self.refresh,
                         name=f"view-{client.client_id}")
        self._loops[client.client_id] = loop
        client.camera.on_update(lambda _: loop.moved())
        loop.moved()

    def _disconnect(self, client) -> None:
        loop = self._loops.pop(client.client_id, None)
        if loop is not None:
            loop.stop()

    def _send(self, client, image: np.ndarray, info: FrameInfo) -> None:
        client.scene.set_background_image(image, format="jpeg", jpeg_quality=90 if info.still else 70)
        if info.still:
            self._status.content = (f"{self.source.status()}  \n"
                                    f"{info.width}×{info.height} in {info.seconds * 1000:.0f} ms")
        with self._cond:
            self.frames_sent += 1
            self._cond.notify_all()
