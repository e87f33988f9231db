"""Browser viewer of a trained (or training) model, rendered by warpgs's own rasterizer through viser.

    warpgs-view --model OUT              # a warpgs-train output folder, or a .ply
    warpgs-train ... train.viewer=true   # the same viewer on the model as it trains

Needs the `viewer` extra (`pip install 'warpgs[viewer]'`); nothing here imports viser until a server starts, so
the camera maths (camera.py) and the render sources (sources.py) work and test without it.

| file | job |
|---|---|
| `deps.py` | import viser, or say which extra to install |
| `camera.py` | viewer camera (camera-to-world, vertical fov, canvas size) -> warpgs viewmat and K; the start pose |
| `sources.py` | what is rendered: a model alone (`render_model`), or a Trainer's (`Trainer.render`, under its lock) |
| `turn_lock.py` | the lock a training run and a viewer take turns on, waiters served in arrival order |
| `frames.py` | one client's render thread: small frames while the camera moves, a full one once it stops |
| `server.py` | the viser server: clients, camera callbacks, the panel |
| `load.py` | `--model PATH` -> a render source, with errors naming the path |
| `live.py` | `train.viewer=true`: the viewer inside the trainer's process |
| `cli.py` | `warpgs-view` |
"""
