"""Import paths from before the package was split into subpackages (warpgs.pipeline, warpgs.train_loop, ...)
keep working: each old name is an alias of its new module, with a DeprecationWarning naming the new path."""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

MOVED = {
    "warpgs.render_surfels": "warpgs.render.surfels",
    "warpgs.pipeline": "warpgs.render.pipeline_gaussians",
    "warpgs.raster_defaults": "warpgs.render.defaults",
    "warpgs.validation": "warpgs.render.validation",
    "warpgs.cpu_threads": "warpgs.render.cpu_threads",
    "warpgs.gaussians": "warpgs.model.gaussians",
    "warpgs.ply": "warpgs.model.ply",
    "warpgs.primitive_math": "warpgs.model.primitive_math",
    "warpgs.environment": "warpgs.model.environment",
    "warpgs.model_render": "warpgs.model.rendering",
    "warpgs.train_setup": "warpgs.train.setup",
    "warpgs.train_loop": "warpgs.train.loop",
    "warpgs.train_state": "warpgs.train.state",
    "warpgs.train_eval": "warpgs.train.evaluation",
    "warpgs.train_guard": "warpgs.train.guard",
    "warpgs.strategy": "warpgs.train.strategy",
    "warpgs.optim": "warpgs.train.optim",
    "warpgs.checkpoint": "warpgs.train.checkpoint",
    "warpgs.extensions": "warpgs.train.extensions",
    "warpgs.config_schema": "warpgs.config.schema",
    "warpgs.config_checks": "warpgs.config.checks",
    "warpgs.user_imports": "warpgs.config.user_imports",
    "warpgs.demo": "warpgs.cli.demo",
    "warpgs.orbit": "warpgs.cli.orbit",
    "warpgs.evaluate": "warpgs.metrics.views",
    "warpgs.depth_metrics": "warpgs.metrics.depth",
    "warpgs.atomic_file": "warpgs.utils.atomic_file",
    "warpgs.progress": "warpgs.utils.progress",
    "warpgs.query": "warpgs.language.query",
    "warpgs.data.colmap": "warpgs.data.formats.colmap",
    "warpgs.data.colmap_check": "warpgs.data.formats.colmap_check",
    "warpgs.data.transforms": "warpgs.data.formats.transforms",
    "warpgs.data.lightfield": "warpgs.data.formats.lightfield",
    "warpgs.data.synthetic": "warpgs.data.formats.synthetic",
    "warpgs.data.raytrace": "warpgs.data.formats.raytrace",
    "warpgs.data.textures": "warpgs.data.formats.textures",
    "warpgs.data.splits": "warpgs.data.formats.splits",
    "warpgs.data.view_files": "warpgs.data.formats.view_files",
    "warpgs.data.image_io": "warpgs.data.formats.image_io",
    "warpgs.data.resize": "warpgs.data.formats.resize",
    "warpgs.data.undistort": "warpgs.data.formats.undistort",
    "warpgs.data.load": "warpgs.data.formats.load",
    "warpgs.data.depth_align": "warpgs.data.depth.align",
    "warpgs.data.depth_estimators": "warpgs.data.depth.estimators",
    "warpgs.data.depth_eval": "warpgs.data.depth.evaluate",
    "warpgs.data.depth_io": "warpgs.data.depth.files",
    "warpgs.data.depth_priors": "warpgs.data.depth.priors",
    "warpgs.data.plane_sweep": "warpgs.data.depth.plane_sweep",
    "warpgs.data.video_depth": "warpgs.data.depth.video_depth",
    "warpgs.data.init_points": "warpgs.data.sfm.init_points",
    "warpgs.data.sim3": "warpgs.data.sfm.sim3",
}


class _AliasLoader(importlib.abc.Loader):
    def __init__(self, new: str):
        self.new = new

    def create_module(self, spec):
        warnings.warn(f"{spec.name} moved to {self.new}; import it from there", DeprecationWarning, stacklevel=3)
        return importlib.import_module(self.new)

    def exec_module(self, module):
        pass  # the new module is already executed


class _MovedFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        new = MOVED.get(fullname)
        if new is None:
            return None
        return importlib.util.spec_from_loader(fullname, _AliasLoader(new))


def install() -> None:
    if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
        sys.meta_path.append(_MovedFinder())
