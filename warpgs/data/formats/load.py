"""`load_scene(path)`: tell what kind of scene folder this is and load it."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from warpgs.data.formats import colmap

from warpgs.data.formats import lightfield
from warpgs.data.formats import llff

from warpgs.data.formats import transforms
from warpgs.data.errors import MissingSceneFile, PathLike, SceneError
from warpgs.data.formats.image_io import list_images
from warpgs.data.scene import Scene


FORMATS = ("lightfield", "transforms", "llff", "colmap", "images")


def detect_format(root: PathLike) -> str:
    """"lightfield", "transforms", "llff", "colmap", "images" (needs SfM); raises for a missing or empty folder.

    poses_bounds.npy wins over a COLMAP model in the same folder: it is what LLFF benchmarks evaluate with (and
    the LLFF loader still takes the model's points when its poses agree). load_scene(..., format="colmap")
    reads the model instead."""
    root = Path(root)
    if not root.exists():
        raise MissingSceneFile(root, "scene folder")
    if not root.is_dir():
        from warpgs.data.video.decode import is_video  # suffixes only: no imageio needed

        if is_video(root):  # data.path=clip.mp4: the video step runs only for --data
            raise SceneError(root, f"a video, not a scene folder: give it as `warpgs-train --data {root}` (frames "
                                   f"and SfM first), or make its scene with `warpgs-process {root} --out DIR`")
        raise SceneError(root, "a scene is a folder, not a file")
    if (root / lightfield.LIGHTFIELD_FILE).is_file():
        return "lightfield"
    if transforms.find_transforms(root):
        return "transforms"
    if llff.find_poses(root) is not None:
        return "llff"
    if colmap.find_model(root) is not None:
        return "colmap"
    images = root / "images"
    if images.is_dir() and list_images(images):
        return "images"
    if list_images(root):
        return "images"
    raise SceneError(root, "no scene found: expected lightfield.json, transforms.json, poses_bounds.npy (LLFF), "
                           "a COLMAP model (sparse/0) or an images/ folder with images")


def load_scene(path: PathLike, *, split=None, n_train=None, downscale: int = 1, undistort: bool = True,
               run_sfm_if_needed: bool = True, format: Optional[str] = None, **kwargs) -> Scene:
    """Load any supported scene folder. Light-field folders use the grid protocol unless split="file"/"all";
    LLFF folders (poses_bounds.npy) hold out every 8th view unless split.json or `split` says otherwise.
    format: one of FORMATS to skip detection (e.g. "colmap" for a folder that also has poses_bounds.npy).

    A folder holding only images (in images/ or at its top level) is reconstructed with pycolmap first
    (written to <folder>/sparse/0 and <folder>/database.db) when run_sfm_if_needed is True.
    Extra keyword arguments go to the specific loader (e.g. background=... for transforms.json).
    """
    root = Path(path)
    if format is not None and format not in FORMATS:
        raise ValueError(f"load_scene: format must be one of {FORMATS} or None, got {format!r}")
    kind = format or detect_format(root)
    if kind == "lightfield":
        if n_train is not None:
            raise ValueError(f"{root}: a light field's training views are its k x k grid; n_train does not apply "
                             "(pass k=... for another grid size)")
        protocol = split or "grid"
        return lightfield.load_lightfield(root, protocol=protocol, downscale=downscale, undistort=undistort,
                                          run_sfm_if_needed=run_sfm_if_needed, **kwargs)
    if kind == "transforms":
        return transforms.load_transforms(root, split=split, n_train=n_train, downscale=downscale,
                                          undistort=undistort, **kwargs)
    if kind == "llff":
        return llff.load_llff(root, split=split, n_train=n_train, downscale=downscale, undistort=undistort, **kwargs)
    if kind == "images":
        if not run_sfm_if_needed:
            raise SceneError(root, "images but no camera poses; run warpgs.data.run_sfm or pass run_sfm_if_needed")
        from warpgs.data.sfm.run import run_sfm

        image_dir = root / "images" if (root / "images").is_dir() else root
        run_sfm(image_dir, root)
        return colmap.load_colmap(root, images_dir=image_dir, split=split, n_train=n_train, downscale=downscale,
                                  undistort=undistort, **kwargs)
    return colmap.load_colmap(root, split=split, n_train=n_train, downscale=downscale, undistort=undistort, **kwargs)
