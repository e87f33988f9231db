"""`warpgs-view --model OUT`: a browser viewer of a trained model (also `python -m warpgs.viewer`)."""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from typing import List, Optional

EXIT_ERROR = 2
SHUTDOWN_SECONDS = 30  # after Ctrl-C, the longest the render threads and the server may take to stop


def _positive(text: str) -> int:
    value = int(text)
    if value < 16:
        raise argparse.ArgumentTypeError(f"expected at least 16 pixels, got {value}")
    return value


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="warpgs-view", description="View a trained model in the browser, rendered "
                                 "by warpgs on the GPU or CPU (needs: pip install 'warpgs[viewer]').")
    ap.add_argument("--model", required=True, help="a warpgs-train output folder (config.yaml + checkpoint.pt or "
                                                   "point_cloud.ply) or a .ply file")
    ap.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1; 0.0.0.0 for "
                                                        "other machines)")
    ap.add_argument("--port", type=int, default=8080, help="port (default 8080; a busy one moves on to the next "
                                                           "free one; 0: any free port)")
    ap.add_argument("--device", help="cpu, cuda or cuda:N (default: CUDA when available)")
    ap.add_argument("--max-res", type=_positive, metavar="N", help="longest image side while the camera moves "
                                                                   "(default 256 on CPU, 1024 on CUDA)")
    ap.add_argument("--still-res", type=_positive, metavar="N", help="longest image side once the camera stops "
                                                                     "(default 640 on CPU, 2048 on CUDA)")
    ap.add_argument("--background", metavar="COLOUR", help="black, white or R,G,B in [0, 1] (default: the run's, "
                                                           "black for a PLY)")
    return ap


def main(argv: Optional[List[str]] = None) -> int:
    args = parser().parse_args(argv)
    from warpgs.viewer.deps import ViewerUnavailable, require_viser
    from warpgs.viewer.load import check_model_path, load_source, parse_background, resolve_device

    try:
        background = parse_background(args.background)
        check_model_path(args.model)
        if not 0 <= args.port <= 65535:
            raise ValueError(f"--port: expected 0..65535, got {args.port}")
        device = resolve_device(args.device)
        require_viser("warpgs-view")
        source = load_source(args.model, device, background)
    except (FileNotFoundError, ValueError, ViewerUnavailable) as e:
        print(f"warpgs-view: error: {e}", file=sys.stderr)
        return EXIT_ERROR

    from warpgs.viewer.server import Viewer, default_resolution

    res = default_resolution(device)
    res.moving = args.max_res or res.moving
    res.still = args.still_res or res.still
    # Ctrl-C (or SIGTERM) only sets an event: a KeyboardInterrupt raised wherever the main thread happens to be
    # could escape the shutdown below (a CI run saw the process end by SIGINT instead of exiting cleanly).
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    viewer = Viewer(source, host=args.host, port=args.port, resolution=res, who="warpgs-view")
    print(f"warpgs-view: {source.status()} on {device}; open {viewer.url} (Ctrl-C to stop)", flush=True)
    try:
        while not stop.wait(3600):
            pass
    finally:
        _exit_if_stuck(SHUTDOWN_SECONDS)
        viewer.close()
    return 0


def _exit_if_stuck(seconds: float) -> None:
    """Ends the process after `seconds` if closing the viewer (render threads, then the web server and the
    interpreter's exit) has not finished by then: the viewer writes nothing, so nothing is lost, and a Ctrl-C that
    does not end the program is worse. (A CI run once saw the process still alive 90 s after Ctrl-C.)"""
    def watchdog():
        print(f"warpgs-view: shutdown took over {seconds:g} s; exiting", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(0)

    timer = threading.Timer(seconds, watchdog)
    timer.daemon = True
    timer.start()


if __name__ == "__main__":
    sys.exit(main())
