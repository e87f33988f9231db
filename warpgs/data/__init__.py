"""Scenes in: COLMAP, transforms.json, light-field arrays, depth priors and a built-in synthetic scene.

Data code imports no Warp; pycolmap and OpenEXR are imported only inside the functions that need them.
"""
from warpgs.data.camera import Camera, look_at, opengl_camtoworld_from_viewmat, viewmat_from_opengl_camtoworld
from warpgs.data.formats.colmap import load_colmap, save_colmap
from warpgs.data.depth.align import DepthAlignment, align_depth_to_points, align_inverse_depth
from warpgs.data.depth.estimators import DepthEstimate, DepthEstimator
from warpgs.data.depth.evaluate import depth_metrics
from warpgs.data.depth.files import read_depth, read_inverse_depth, write_exr
from warpgs.data.depth.priors import compute_depth_priors
from warpgs.data.errors import DepthModelUnavailable, MissingSceneFile, SceneError
from warpgs.data.sfm.init_points import initial_points, points_from_depth, random_points
from warpgs.data.formats.lightfield import grid_protocol_split, load_lightfield, pseudo_video_order
from warpgs.data.formats.load import detect_format, load_scene
from warpgs.data.depth.plane_sweep import PlaneSweepStereo
from warpgs.data.points import PointCloud
from warpgs.data.scene import MapFormat, Scene, View, ViewFiles
from warpgs.data.sfm.run import run_sfm
from warpgs.data.sfm.sim3 import pose_errors, umeyama
from warpgs.data.formats.splits import llff_split
from warpgs.data.formats.synthetic import default_scene, make_synthetic_scene, write_synthetic_scene
from warpgs.data.formats.transforms import load_transforms, save_transforms
from warpgs.data.depth.video_depth import VideoDepthAnything

__all__ = [
    "Camera", "look_at", "opengl_camtoworld_from_viewmat", "viewmat_from_opengl_camtoworld",
    "load_colmap", "save_colmap", "load_transforms", "save_transforms", "load_lightfield", "load_scene",
    "detect_format", "run_sfm", "Scene", "View", "ViewFiles", "MapFormat", "PointCloud",
    "llff_split", "grid_protocol_split", "pseudo_video_order",
    "read_depth", "read_inverse_depth", "write_exr", "DepthAlignment", "align_inverse_depth",
    "align_depth_to_points", "DepthEstimate", "DepthEstimator", "PlaneSweepStereo", "VideoDepthAnything",
    "compute_depth_priors", "depth_metrics", "initial_points", "points_from_depth", "random_points",
    "make_synthetic_scene", "write_synthetic_scene", "default_scene", "pose_errors", "umeyama",
    "SceneError", "MissingSceneFile", "DepthModelUnavailable",
]
