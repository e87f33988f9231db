"""The real scenes of the sparse-view benchmark (benchmarks/sparse.py): where public copies are, and a small copy of
each at the benchmark's resolution that a GPU machine can receive (64 MiB a call, for everything carried).

    python benchmarks/sparse_data.py sources                           # the known public copies
    python benchmarks/sparse_data.py extract MIRROR data/leaves data/raw/leaves   # a folder of a fetched repo
    python benchmarks/sparse_data.py llff data/raw/leaves data/sparse/leaves --jpeg 98   # images_8 + poses + ref.
    python benchmarks/sparse_data.py gather data/raw/bonsai_src data/bonsai800/images --skip images  # for SfM
    python benchmarks/sparse_data.py orbit data/raw/stitch/images data/stitch/images --factor 2  # numbered, for SfM
    python benchmarks/sparse_data.py colmap data/bonsai800 data/sparse/bonsai800  # images + sparse/0, as they are
    python benchmarks/sparse_data.py nex data/raw/room_nex data/raw/room_llff    # NeX's layout -> standard LLFF
    python benchmarks/sparse_data.py size data/sparse/*                           # MiB per scene and in all

MIRROR is the bare git directory `fetch` made (/work/.mirror/<owner>+<name>/repo); a snapshot lacks files of 4 MiB
and more, which `extract` names and skips (often sparse/0/images.bin). `llff` writes images_<factor>/<name> at
1/factor of the poses' full size (from the source's own images_<factor> when it has them at that size, else
area-resized from whichever complete image folder it has), PNG or, with --jpeg Q,
JPEG (half the bytes), copies poses_bounds.npy, and turns the source's SfM model (sparse/0, made from every view)
into reference_depth.npz: the depth of its points in each view that saw them, what the benchmark scores test-view
depth at (never used for training). `colmap` copies images/ and sparse/0 unchanged (a 360° capture is read at
data.downscale, e.g. 2 for bonsai800's 800x533 photos, ~FSGS's images_8 size). data/ is git-ignored: nothing
here is committed.
"""
from __future__ import annotations

import argparse
import io
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from warpgs.data.errors import SceneError  # noqa: E402
from warpgs.data.formats.image_io import list_images, read_image, to_uint8, write_png  # noqa: E402
from warpgs.data.formats.resize import resize_area  # noqa: E402
from warpgs.utils.atomic_file import atomic_write_bytes  # noqa: E402

CARRY_BUDGET_MIB = 64  # what one device call can receive: tracked files + carried folders
REFERENCE_FILE = "reference_depth.npz"
MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin", "cameras.txt", "images.txt", "points3D.txt")


@dataclass(frozen=True)
class Source:
    repo: str  # owner/name on GitHub
    path: str  # the scene's folder in it
    kind: str  # "llff" (poses_bounds.npy), "nex" (NeX's layout: `nex` first), "colmap" (sparse/0), or "images" (no
    # poses: run SfM first)
    note: str


# Public copies found with the search tool. fern, flower, horns and orchids are the NeRF release's own files; room,
# trex and fortress are NeX's release (its own COLMAP poses, undistorted ~1000x750 images: `nex` makes standard LLFF
# folders of them, then `llff --factor 2`). No photographic copy of leaves was found: the only one fetched
# (bwnebs1/23-2_DSL_Modeling_3D_Style_with_NeRF, like its room, trex and orchids) holds style-transferred images,
# each view painted on its own, so no model can render a held-out view of them; it is listed to be avoided.
SOURCES = {
    "fern": Source("luo-ziyuan/CopyRNeRF-code", "data/nerf_llff_data/fern", "llff",
                   "original images_4/images_8 PNGs, sparse/0 points3D.bin (no images.bin)"),
    "flower": Source("zhelianl-zl/deeplearning_Nerf", "data/flower", "llff",
                     "original images_8 PNGs (image000.png ...), sparse/0 without images.bin (a snapshot lacks it)"),
    "horns": Source("Bussler/CustomNeRF", "data/horns", "llff",
                    "images/ holds the 504x378 images_8 PNGs; no SfM model (no depth reference)"),
    "orchids": Source("Zephyrmcb/NeRF-Pytorch", "data/nerf_llff_data/orchids", "llff",
                      "original poses and photos, images_8 as 504x378 JPEGs; sparse/0 without images.bin: prepare "
                      "without it (--triangulate) for the depth reference"),
    "room": Source("Javlon3002/For_NeX", "dataset/room", "nex",
                   "NeX's release: 41 undistorted 996x746 JPEGs (img001..), [N, 14] poses, hwf_cxcy.npy; `nex`, "
                   "then `llff --factor 2 --jpeg 98 --triangulate`, read as PATH@2"),
    "trex": Source("Javlon3002/For_NeX", "dataset/trex", "nex",
                   "NeX's release: 55 undistorted 1002x751 images; as room"),
    "fortress": Source("Javlon3002/For_NeX", "dataset/fortress", "nex",
                       "NeX's release: 42 undistorted 1004x753 images; as room"),
    "leaves (stylised)": Source("bwnebs1/23-2_DSL_Modeling_3D_Style_with_NeRF", "data/leaves", "llff",
                                "NOT usable: style-transferred 800x600 JPEGs, every view painted separately (the "
                                "same repository's room, trex and orchids too)"),
    "phone64": Source("Scodive/Data", ".", "llff",
                      "64 phone photos around a subject (360-ish), 1920x1080, poses_bounds.npy, sparse/0 without "
                      "images.bin; the issue's capture: prepare with --factor 4 --keep-images, read it as PATH@4"),
    "bonsai800": Source("EricXu23/Bonsaidownload", ".", "images",
                        "Mip-NeRF 360 bonsai, 292 photos at 800x533, no usable poses: run SfM "
                        "(benchmarks/sfm.py --mapper global) into sparse/0 first; gather --skip images"),
    "figurine": Source("5697526/NeRF-TensoRF", "images", "images",
                       "80 phone photos (1080x1920) walking around a figurine on a table (two passes in places), "
                       "named 1.jpg..80.jpg; its sparse/0 lacks images.bin and gives each photo its own focal "
                       "length: `orbit --factor 2`, then SfM (--mapper global: 80/80 registered), read as PATH@2"),
    "stitch": Source("jianzhengjie/Gaussian-Splatting-", "data/sparse/0/images", "images",
                     "82 video frames (1440x1440) around a plush toy on a table, one loop; the repository's model "
                     "files are truncated in the snapshot: `orbit --factor 2`, then SfM (--mapper global: 82/82), "
                     "read as PATH@2"),
}


def extract(mirror: Path, path: str, dest: Path, commit: str = "HEAD") -> tuple[Path, list[str]]:
    """Copy one folder of a fetched bare repository (its files at `commit`) into dest. Returns (dest, the files
    the snapshot lacks): a snapshot leaves out files of 4 MiB and more, so these are skipped, named."""
    mirror, dest = Path(mirror), Path(dest)
    if not (mirror / "HEAD").is_file():
        raise SystemExit(f"{mirror}: not a bare git directory (expected the `fetch` result, .../repo)")
    git = ["git", "--git-dir", str(mirror)]
    prefix = "" if path in ("", ".") else path.rstrip("/") + "/"
    listing = subprocess.run(git + ["ls-tree", "-r", "-z", commit, "--", prefix or "."], capture_output=True)
    if listing.returncode != 0:
        raise SystemExit(f"{mirror}: cannot list {commit}:{path}: {listing.stderr.decode(errors='replace').strip()}")
    missing = []
    for entry in filter(None, listing.stdout.split(b"\0")):
        meta, name = entry.decode().split("\t", 1)
        _, kind, obj = meta.split()
        if kind != "blob":
            continue
        blob = subprocess.run(git + ["cat-file", "blob", obj], capture_output=True)
        if blob.returncode != 0:
            missing.append(name)
            continue
        target = dest / name[len(prefix):]
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(blob.stdout)
    return dest, missing


def gather_images(src: Path, dest: Path, skip=()) -> list[Path]:
    """Every image under src, except in the `skip` subfolders, into dest (one folder, for SfM), by file name; two
    different files of one name are an error. EricXu23/Bonsaidownload spreads bonsai800's 292 photos over its root
    and input/ (its images/ holds 3 undistorted 699x461 outputs: skip it)."""
    from warpgs.data.formats.image_io import IMAGE_EXTENSIONS

    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    seen: dict = {}
    for p in sorted(Path(src).rglob("*")):
        if not p.is_file() or p.suffix not in IMAGE_EXTENSIONS or dest in p.parents:
            continue
        if any(Path(src) / k in p.parents for k in skip):
            continue
        if p.name in seen and seen[p.name].read_bytes() != p.read_bytes():
            raise SystemExit(f"{p} and {seen[p.name]}: two different images named {p.name}")
        seen[p.name] = p
        shutil.copyfile(p, dest / p.name)
    return sorted(dest / n for n in seen)


def _source_images(src: Path, n: int, factor: int, size: tuple[int, int]) -> tuple[list[Path], bool]:
    """(the n images in pose order, whether they are already `size`): images_<factor> when complete at that size,
    else images/, else any complete images_N folder (the largest)."""
    candidates = [src / f"images_{factor}", src / "images"] + sorted(src.glob("images_*"))
    for folder in candidates:
        if not folder.is_dir():
            continue
        files = list_images(folder)
        if len(files) != n:
            continue
        w, h = read_image(files[0])[0].shape[1::-1]
        return files, (w, h) == size
    raise SystemExit(f"{src}: no image folder holds one image per row of poses_bounds.npy ({n})")


def prepare_llff(src: Path, out: Path, factor: int = 8, jpeg_quality: int = 0, keep_model: bool = False,
                 triangulate: bool = False, keep_images: bool = False) -> Path:
    """An LLFF scene trimmed to one resolution: images_<factor>/ + poses_bounds.npy, and, when the source has an SfM
    model, reference_depth.npz (its points' depth in every view, what the benchmark scores depth at) instead of the
    model (kept too with keep_model). jpeg_quality > 0 writes JPEGs (4:4:4) instead of PNGs, about half the bytes:
    at 98 they differ from the PNGs by ~46 dB PSNR (fern, horns, room, trex at 1/8). triangulate: a source without
    a model gets one for the reference from every view's known pose (pycolmap; horns: a few minutes on 2 cores).
    keep_images: copy the source's images/ as they are instead (no images_<factor>): the presets triangulate their
    initial points from the scene's native images (up to 1600 px), and 3 views of phone64 at 1/4 give fewer than
    the 100 points they need (93), where its 1920x1080 photos gave the issue's runs enough."""
    src, out = Path(src), Path(out)
    poses_path = src / "poses_bounds.npy"
    if not poses_path.is_file():
        raise SystemExit(f"{src}: no poses_bounds.npy (not an LLFF scene)")
    poses = np.load(poses_path)
    if poses.ndim != 2 or poses.shape[1] != 17:
        raise SystemExit(f"{poses_path}: expected an [N, 17] array, got {poses.shape}")
    if keep_images:  # the full-size images as they are: the loader resizes them (and caches the result)
        if not (src / "images").is_dir():
            raise SystemExit(f"{src}: --keep-images, but there is no images/ folder")
        shutil.copytree(src / "images", out / "images", dirs_exist_ok=True)
    else:
        _write_scaled_images(src, out, len(poses), poses[0, :15].reshape(3, 5)[:2, 4], factor, jpeg_quality)
    shutil.copyfile(poses_path, out / "poses_bounds.npy")
    model = src / "sparse" / "0"
    if model.is_dir():
        (out / "sparse" / "0").mkdir(parents=True, exist_ok=True)
        for name in MODEL_FILES:
            if (model / name).is_file():
                shutil.copyfile(model / name, out / "sparse" / "0" / name)
        try:
            write_reference_depth(out, factor)
        except SceneError as e:  # e.g. no images.bin and bounds that do not fit the sorted-order guess
            print(f"{out}: no depth reference ({e})", file=sys.stderr)
        if not keep_model:
            shutil.rmtree(out / "sparse")
    elif triangulate:
        import tempfile

        from warpgs.data import load_scene
        from warpgs.data.sfm.triangulate import triangulate_scene

        scene = load_scene(out, split="all", downscale=factor)
        with tempfile.TemporaryDirectory(prefix="sparse-data-tri-") as tmp:
            tri = triangulate_scene(scene, tmp, views=range(len(scene)))
            print(f"{out}: triangulated {len(tri.points)} points from all {len(scene)} views "
                  f"({tri.mean_error:.2f} px) for the depth reference", file=sys.stderr)
            write_reference_depth(out, factor, Path(tmp) / "model")
    return out


def _write_scaled_images(src: Path, out: Path, n: int, hw, factor: int, jpeg_quality: int) -> None:
    """images_<factor>/: the n images at 1/factor of the poses' full size, named after the full-size files."""
    h, w = hw
    size = (max(1, round(w / factor)), max(1, round(h / factor)))
    files, same = _source_images(src, n, factor, size)
    # Name each image after the full-size file it belongs to when the scene has them (the SfM model names those).
    full = list_images(src / "images") if (src / "images").is_dir() else []
    names = [p.stem for p in full] if len(full) == len(files) else [p.stem for p in files]
    folder = out / f"images_{factor}"
    folder.mkdir(parents=True, exist_ok=True)
    for f, name in zip(files, names):
        rgb, _ = read_image(f)
        rgb = rgb if same else resize_area(rgb, *size)
        if jpeg_quality:
            atomic_write_bytes(folder / f"{name}.jpg", jpeg_bytes(rgb, jpeg_quality))
        else:
            write_png(folder / f"{name}.png", rgb)


def jpeg_bytes(rgb: np.ndarray, quality: int) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(to_uint8(rgb)).save(buf, "JPEG", quality=quality, subsampling=0)
    return buf.getvalue()


def write_reference_depth(scene_dir: Path, downscale: int, model_dir=None) -> Path:
    """reference_depth.npz: per view name, the [K, 3] (column, row, camera z) of the scene's SfM points its track
    saw, at the served resolution (the nearest point per pixel), from warpgs.data.depth.reference_points. A few
    hundred KiB instead of a model of several MiB; benchmarks/sparse.py reads it back as sparse depth maps."""
    from warpgs.data import load_scene
    from warpgs.data.depth.reference_points import sparse_depth_map, view_reference_points

    scene = load_scene(scene_dir, split="llff", downscale=downscale)
    points, per_view = view_reference_points(scene, model_dir)
    arrays = {}
    for v, name in enumerate(scene.names):
        depth = sparse_depth_map(scene.cameras[v], points.xyz[per_view[v]])
        rows, cols = np.nonzero(depth)
        arrays[name] = np.stack([cols, rows, depth[rows, cols]], axis=1).astype(np.float32)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays, __size__=np.array([scene.cameras[0].width, scene.cameras[0].height]))
    path = Path(scene_dir) / REFERENCE_FILE
    atomic_write_bytes(path, buf.getvalue())
    return path


def read_reference_depth(scene_dir: Path, names, width: int, height: int) -> dict:
    """{view name: [H, W] float32 sparse depth (0 = unknown)} from reference_depth.npz; a size other than the
    scene's served one is an error naming the file."""
    path = Path(scene_dir) / REFERENCE_FILE
    with np.load(path) as data:
        made = tuple(int(x) for x in data["__size__"])
        if made != (width, height):
            raise SystemExit(f"{path}: made for {made[0]}x{made[1]} images, but the scene is served at "
                             f"{width}x{height}: give the downscale it was made at (--scenes FOLDER@N), or make it "
                             f"again at this size")
        out = {}
        for name in names:
            depth = np.zeros((height, width), np.float32)
            if name in data:
                c, r, z = data[name].T
                depth[r.astype(np.int64), c.astype(np.int64)] = z
            out[name] = depth
    return out


def prepare_colmap(src: Path, out: Path) -> Path:
    """A COLMAP scene copied as it is (images/ and sparse/0's model files only)."""
    src, out = Path(src), Path(out)
    if not (src / "sparse" / "0").is_dir() or not (src / "images").is_dir():
        raise SystemExit(f"{src}: expected images/ and sparse/0 (run SfM on the images first)")
    shutil.copytree(src / "images", out / "images", dirs_exist_ok=True)
    (out / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    for name in MODEL_FILES:
        if (src / "sparse" / "0" / name).is_file():
            shutil.copyfile(src / "sparse" / "0" / name, out / "sparse" / "0" / name)
    return out


def folder_mib(folder: Path) -> float:
    return sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file()) / 2**20


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("sources", help="print the known public copies")
    e = sub.add_parser("extract", help="copy one folder of a fetched bare repository")
    e.add_argument("mirror"), e.add_argument("path"), e.add_argument("dest")
    e.add_argument("--commit", default="HEAD")
    p = sub.add_parser("llff", help="trim an LLFF scene to images_<factor> + poses (+ sparse/0)")
    p.add_argument("src"), p.add_argument("out")
    p.add_argument("--factor", type=int, default=8)
    p.add_argument("--jpeg", type=int, default=0, metavar="Q", help="write JPEGs of quality Q (default: PNG)")
    p.add_argument("--keep-model", action="store_true", help="keep sparse/0 beside reference_depth.npz")
    p.add_argument("--keep-images", action="store_true",
                   help="copy images/ as they are instead of writing images_<factor> (full-size native images)")
    p.add_argument("--triangulate", action="store_true",
                   help="no model in SRC: triangulate every view's known pose for the depth reference")
    g = sub.add_parser("gather", help="every image under SRC into one folder DEST (for SfM)")
    g.add_argument("src"), g.add_argument("dest")
    g.add_argument("--skip", action="append", default=[], help="a subfolder of SRC to leave out (repeatable)")
    o = sub.add_parser("orbit", help="a walk-around capture's photos, renamed in capture order, for SfM "
                                     "(sparse_data_orbit.py)")
    o.add_argument("src"), o.add_argument("dest")
    o.add_argument("--factor", type=int, default=1, help="area-average to 1/factor of the size first")
    x = sub.add_parser("nex", help="an LLFF scene in NeX's layout as a standard LLFF folder (sparse_data_nex.py)")
    x.add_argument("src"), x.add_argument("out")
    x.add_argument("--jpeg", type=int, default=98, metavar="Q", help="JPEG quality of the cropped images")
    c = sub.add_parser("colmap", help="copy a COLMAP scene's images/ and sparse/0")
    c.add_argument("src"), c.add_argument("out")
    s = sub.add_parser("size", help="MiB per scene folder and in all, against the carry budget")
    s.add_argument("folders", nargs="+")
    args = ap.parse_args(argv)
    if args.cmd == "sources":
        for name, src in SOURCES.items():
            print(f"{name:10s} {src.kind:7s} github:{src.repo} {src.path}  ({src.note})")
    elif args.cmd == "extract":
        dest, missing = extract(Path(args.mirror), args.path, Path(args.dest), args.commit)
        lacks = f" (the snapshot lacks {len(missing)} file(s): {', '.join(missing[:5])})" if missing else ""
        print(f"{dest}{lacks}")
    elif args.cmd == "nex":
        from sparse_data_nex import convert

        print(f"{convert(Path(args.src), Path(args.out), args.jpeg)}: {folder_mib(Path(args.out)):.1f} MiB")
    elif args.cmd == "orbit":
        from sparse_data_orbit import orbit_images

        print(f"{args.dest}: {len(orbit_images(Path(args.src), Path(args.dest), args.factor))} images")
    elif args.cmd == "gather":
        print(f"{args.dest}: {len(gather_images(Path(args.src), Path(args.dest), args.skip))} images")
    elif args.cmd in ("llff", "colmap"):
        out = (prepare_llff(args.src, args.out, args.factor, args.jpeg, args.keep_model, args.triangulate,
                            args.keep_images) if args.cmd == "llff"
               else prepare_colmap(args.src, args.out))
        print(f"{out}: {folder_mib(out):.1f} MiB")
    else:
        total = 0.0
        for f in args.folders:
            mib = folder_mib(Path(f))
            total += mib
            print(f"{f}: {mib:.1f} MiB")
        print(f"total {total:.1f} MiB of the {CARRY_BUDGET_MIB} MiB a device call can receive"
              + ("  ** over: carry fewer scenes per call **" if total > CARRY_BUDGET_MIB else ""))


if __name__ == "__main__":
    main()
