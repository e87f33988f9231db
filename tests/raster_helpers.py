"""Calls the Warp op and the float64 reference on the same scene dict."""
import torch

from reference import render_reference
from warpgs import rasterize

ALL_OUTPUTS = ("rgb", "alpha", "depth", "inv_depth", "features")


def render_ours(scene, outputs, background=None, **kw):
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    return rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], s["viewmat"], s["K"],
                     s["width"], s["height"], sh_degree=s["sh_degree"], features=s["features"],
                     background=None if background is None else background.float(), outputs=outputs, **kw)


def render_ref(scene, background=None):
    return render_reference(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                            scene["viewmat"], scene["K"], scene["width"], scene["height"],
                            sh_degree=scene["sh_degree"], features=scene["features"], background=background)


def requested(scene):
    return tuple(o for o in ALL_OUTPUTS if o != "features" or scene["features"] is not None)
