"""Readers under fuzzing: truncated or corrupted COLMAP binaries, transforms.json, PLY files, EXR and .npy depth
maps either load or raise SceneError / ValueError naming the file; never a hang, a crash or a dependency's own
exception (struct.error, IndexError, KeyError, UnicodeDecodeError, OverflowError, MemoryError, ...).

Each reader gets a valid file written by our own writers (or, for COLMAP, by pycolmap) and hypothesis corrupts
it: truncation, overwritten bytes, extreme integers over count fields, inserted and deleted bytes, and for the
text formats, edited header lines or JSON values. Examples are few and derandomized (CI has 2 cores). A reader
stuck in native code cannot be interrupted from Python, so each example runs under faulthandler's watchdog:
a hang dumps every thread's traceback and ends the run instead of stalling CI.
"""
import faulthandler
import json
import shutil
import struct
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from warpgs.data.camera import Camera
from warpgs.data.depth.files import read_depth_file, write_exr
from warpgs.data.errors import MissingSceneFile, SceneError
from warpgs.data.formats.colmap import cameras_from_model, points_from_model, read_model, save_colmap
from warpgs.data.formats.ply_points import read_ply_points
from warpgs.data.formats.transforms import load_transforms, save_transforms
from warpgs.data.points import PointCloud
from warpgs.model.gaussians import GaussianModel, load_ply

FUZZ = settings(max_examples=60, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
HANG_SECONDS = 60  # one example takes milliseconds; a minute means a reader is stuck
EXTREME = [0, 1, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**40, 2**63 - 1, 2**63, 2**64 - 1]
_ROOT = Path(tempfile.mkdtemp(prefix="warpgs-fuzz-"))


_WATCHDOG_FD = [None]  # where a hang's tracebacks go: pytest's copy of the real stderr (captured output dies with us)


@pytest.fixture(autouse=True, scope="module")
def _watchdog_fd(pytestconfig):
    try:
        from _pytest.faulthandler import fault_handler_stderr_fd_key

        _WATCHDOG_FD[0] = pytestconfig.stash[fault_handler_stderr_fd_key]
    except (ImportError, KeyError):  # another pytest: the tracebacks may then be lost with the captured output
        _WATCHDOG_FD[0] = None


@contextmanager
def no_hang():
    fd = _WATCHDOG_FD[0]
    faulthandler.dump_traceback_later(HANG_SECONDS, exit=True, **({} if fd is None else {"file": fd}))
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


@contextmanager
def scratch():
    """A fresh folder per example (hypothesis examples cannot use function-scoped fixtures)."""
    path = Path(tempfile.mkdtemp(dir=_ROOT))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


@st.composite
def corrupted(draw, data: bytes, int_widths=(4, 8)):
    """`data` damaged one to three times: truncated, bytes overwritten, an extreme little-endian integer written
    over a (likely count) field, bytes inserted or deleted."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["truncate", "overwrite", "integer", "insert", "delete"]))
        at = draw(st.integers(0, max(len(out) - 1, 0)))
        if kind == "truncate":
            del out[at:]
        elif kind == "overwrite":
            chunk = draw(st.binary(min_size=1, max_size=8))
            out[at:at + len(chunk)] = chunk
        elif kind == "integer":
            width = draw(st.sampled_from(int_widths))
            value = draw(st.sampled_from(EXTREME)) % (1 << (8 * width))
            out[at:at + width] = value.to_bytes(width, "little")
        elif kind == "insert":
            out[at:at] = draw(st.binary(min_size=1, max_size=16))
        else:
            del out[at:at + draw(st.integers(1, 16))]
    if bytes(out) == data:
        out = out[:-1]  # always damaged
    return bytes(out)


def assert_names(exc: BaseException, *paths: Path):
    """The error is ours (SceneError, or a plain ValueError from the PLY reader) and names one of `paths`."""
    assert type(exc) in (SceneError, ValueError, MissingSceneFile), f"{type(exc).__name__}: {exc}"
    assert any(str(p) in str(exc) for p in paths), f"error does not name {[str(p) for p in paths]}: {exc}"


# ----- COLMAP binaries -------------------------------------------------------------------------------------------
def _colmap_model() -> dict:
    cameras = []
    for i in range(3):
        viewmat = np.eye(4)
        viewmat[0, 3], viewmat[2, 3] = 0.1 * i, 3.0
        distorted = i == 2
        cameras.append(Camera(np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]]), viewmat, 32, 24,
                              name=f"im{i}.png", model="OPENCV" if distorted else "PINHOLE",
                              distortion=(0.01, 0.0, 0.0, 0.0) if distorted else ()))
    rng = np.random.default_rng(0)
    points = PointCloud(rng.normal(size=(6, 3)), rng.random((6, 3)), [np.arange(6), np.arange(3), np.arange(2, 6)])
    model = save_colmap(cameras, _ROOT / "colmap_base", points, binary=True)
    return {p.name: p.read_bytes() for p in sorted(model.iterdir())}


COLMAP = _colmap_model()


def read_colmap(model_dir: Path):
    rec = read_model(model_dir)
    cameras, ids = cameras_from_model(rec, model_dir / "images", model_dir)
    return cameras, points_from_model(rec, ids, model_dir)


def test_colmap_base_model_reads():
    assert set(COLMAP) == {"cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin"}  # pycolmap 4
    with scratch() as d:
        for name, data in COLMAP.items():
            (d / name).write_bytes(data)
        cameras, points = read_colmap(d)
    assert [c.name for c in cameras] == ["im0.png", "im1.png", "im2.png"] and len(points) == 6


@FUZZ
@given(st.data())
def test_corrupted_colmap_binaries(data):
    name = data.draw(st.sampled_from(sorted(COLMAP)))
    damaged = data.draw(corrupted(COLMAP[name]))
    with scratch() as d, no_hang():
        for other, raw in COLMAP.items():
            (d / other).write_bytes(damaged if other == name else raw)
        try:
            read_colmap(d)
        except Exception as exc:  # noqa: BLE001 -- the point: which exceptions escape
            assert_names(exc, *(d / n for n in COLMAP))


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.sampled_from(["cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin"]), st.data())
def test_truncated_colmap_binaries_name_the_file(name, data):
    """Truncation is the common accident (a copy cut short): the error must blame that very file."""
    raw = COLMAP[name]
    cut = data.draw(st.integers(0, len(raw) - 1))
    with scratch() as d, no_hang():
        for other, content in COLMAP.items():
            (d / other).write_bytes(content[:cut] if other == name else content)
        with pytest.raises(SceneError) as exc:
            read_colmap(d)
    assert str(d / name) in str(exc.value)


@pytest.mark.parametrize("name,offset,what", [
    ("frames.bin", 0, "frames"),  # pycolmap loops 2^63 times (it hung)
    ("points3D.bin", 0, "points"),
    ("images.bin", 0, "images"),
    ("cameras.bin", 0, "cameras"),
])
def test_huge_colmap_counts_fail_fast(name, offset, what):
    raw = bytearray(COLMAP[name])
    raw[offset:offset + 8] = struct.pack("<Q", 2**63)
    with scratch() as d, no_hang():
        for other, content in COLMAP.items():
            (d / other).write_bytes(bytes(raw) if other == name else content)
        with pytest.raises(SceneError, match=f"declares {2**63} {what}") as exc:
            read_colmap(d)
    assert str(d / name) in str(exc.value)


def test_unterminated_image_name_fails_fast():
    """pycolmap reads an image name byte by byte until a NUL and never stops at the end of the file."""
    raw = COLMAP["images.bin"]
    damaged = raw[:raw.index(b"im0.png")] + b"x" * 200  # the first name runs to the end of the file
    with scratch() as d, no_hang():
        for other, content in COLMAP.items():
            (d / other).write_bytes(damaged if other == "images.bin" else content)
        with pytest.raises(SceneError, match="no terminating NUL") as exc:
            read_colmap(d)
    assert str(d / "images.bin") in str(exc.value)


# ----- transforms.json ---------------------------------------------------------------------------------------------
def _transforms_scene() -> Path:
    root = _ROOT / "transforms_base"
    (root / "images").mkdir(parents=True)
    cameras = []
    for i in range(2):
        viewmat = np.eye(4)
        viewmat[0, 3], viewmat[2, 3] = 0.2 * i, 2.0
        cameras.append(Camera(np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]]), viewmat, 16, 12, name=f"v{i}.png"))
        Image.fromarray(np.full((12, 16, 3), 40 * i, np.uint8)).save(root / "images" / f"v{i}.png")
    save_transforms(cameras, root / "transforms.json")
    return root


TRANSFORMS_ROOT = _transforms_scene()
TRANSFORMS = json.loads((TRANSFORMS_ROOT / "transforms.json").read_text())

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12) | st.sampled_from(["OPENCV_FISHEYE", "PINHOLE", "./images/v0", "../..", "a" * 300]),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
    max_leaves=8)


@st.composite
def edited_transforms(draw) -> bytes:
    doc = json.loads(json.dumps(TRANSFORMS))
    kind = draw(st.sampled_from(["value", "value", "delete", "bytes", "nesting"]))
    if kind == "nesting":
        return b'{"frames": ' + b"[" * draw(st.integers(1000, 100000)) + b"]"
    if kind == "bytes":
        return draw(corrupted(json.dumps(doc).encode(), int_widths=(1,)))
    frame = draw(st.integers(0, len(doc["frames"]) - 1))
    keys = ["frames", "top"] + [f"frame:{k}" for k in doc["frames"][frame]]
    key = draw(st.sampled_from(keys + [f"frame:{k}" for k in ("camera_angle_x", "k1", "k3", "k4", "camera_model",
                                                              "depth_file_path", "mask_path", "w")]
                               + ["top:ply_file_path", "top:depth_unit_scale_factor", "top:fl_x"]))
    where, _, name = key.partition(":")
    target = doc if where in ("top", "frames") else doc["frames"][frame]
    name = name or "frames"
    if kind == "delete":
        target.pop(name, None)
    else:
        target[name] = draw(json_values)
    return json.dumps(doc, allow_nan=True).encode()


@FUZZ
@given(edited_transforms())
def test_corrupted_transforms_json(raw):
    with scratch() as d, no_hang():
        root = Path(shutil.copytree(TRANSFORMS_ROOT, d / "scene"))
        (root / "transforms.json").write_bytes(raw)
        try:
            load_transforms(root)
        except Exception as exc:  # noqa: BLE001
            # Most errors name transforms.json; a valid entry that points at a missing or mis-sized file (an
            # image, a depth map) names that file instead.
            assert_names(exc, root)


# ----- PLY: the trainer's 3DGS/2DGS files, and scenes' point clouds -----------------------------------------------
def _ply_base() -> bytes:
    g = torch.Generator().manual_seed(0)
    model = GaussianModel(torch.randn(5, 3, generator=g), torch.randn(5, 3, generator=g), torch.randn(5, 4, generator=g),
                          torch.randn(5, generator=g), torch.randn(5, 1, 3, generator=g), torch.randn(5, 3, 3, generator=g))
    model.add_extra("language", torch.randn(5, 2, generator=g))
    model.save_ply(_ROOT / "base.ply")
    return (_ROOT / "base.ply").read_bytes()


PLY = _ply_base()
PLY_HEADER_END = PLY.index(b"end_header\n") + len(b"end_header\n")


@st.composite
def edited_ply(draw) -> bytes:
    """Header lines edited (tokens replaced, lines dropped or repeated) or the whole file damaged bytewise."""
    if draw(st.booleans()):
        return draw(corrupted(PLY))
    lines = PLY[:PLY_HEADER_END].decode().splitlines()
    i = draw(st.integers(0, len(lines) - 1))
    kind = draw(st.sampled_from(["token", "drop", "repeat"]))
    if kind == "drop":
        del lines[i]
    elif kind == "repeat":
        lines.insert(i, lines[i])
    else:
        words = lines[i].split() or [""]
        j = draw(st.integers(0, len(words) - 1))
        words[j] = draw(st.sampled_from(["-1", "0", "99999999999999", "list", "uchar", "double", "vertex", "face",
                                         "scale_0", "ascii", "f_rest_99999999999", "", "\u00e9"]))
        lines[i] = " ".join(words)
    return ("\n".join(lines) + "\n").encode("utf-8") + PLY[PLY_HEADER_END:]


@FUZZ
@given(edited_ply())
def test_corrupted_gaussian_ply(raw):
    with scratch() as d, no_hang():
        path = d / "point_cloud.ply"
        path.write_bytes(raw)
        try:
            model = load_ply(path)
        except Exception as exc:  # noqa: BLE001
            assert_names(exc, path)
        else:
            assert all(torch.isfinite(p).all() for p in model.params.values())


def _points_ply() -> bytes:
    xyz = np.random.default_rng(1).normal(size=(6, 3)).astype("<f4")
    rgb = np.random.default_rng(2).integers(0, 255, (6, 3)).astype("u1")
    rows = np.empty(6, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, c in enumerate("xyz"):
        rows[c] = xyz[:, k]
    for k, c in enumerate(("red", "green", "blue")):
        rows[c] = rgb[:, k]
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 6\n" + "".join(
        f"property {t} {n}\n" for t, n in [("float", "x"), ("float", "y"), ("float", "z"), ("uchar", "red"),
                                            ("uchar", "green"), ("uchar", "blue")]) + "end_header\n")
    return head.encode() + rows.tobytes()


POINTS_PLY = _points_ply()


@FUZZ
@given(corrupted(POINTS_PLY))
def test_corrupted_point_cloud_ply(raw):
    with scratch() as d, no_hang():
        path = d / "sparse_pc.ply"
        path.write_bytes(raw)
        try:
            read_ply_points(path)
        except Exception as exc:  # noqa: BLE001
            assert_names(exc, path)


def test_point_cloud_ply_with_a_huge_vertex_count():
    """pycolmap reserves the declared count before reading: 2^32 vertices was a std::bad_alloc (MemoryError)."""
    with scratch() as d, no_hang():
        path = d / "sparse_pc.ply"
        path.write_bytes(POINTS_PLY.replace(b"element vertex 6", b"element vertex 4294967296"))
        with pytest.raises(SceneError, match="declares 4294967296 vertices") as exc:
            read_ply_points(path)
    assert str(path) in str(exc.value)


# ----- depth maps: EXR and .npy ---------------------------------------------------------------------------------
def _depth_files() -> dict:
    depth = np.random.default_rng(3).uniform(0.5, 5.0, (12, 10)).astype(np.float32)
    write_exr(_ROOT / "d.exr", depth, "depth", valid=np.ones_like(depth, bool))
    np.save(_ROOT / "d.npy", depth)
    return {".exr": (_ROOT / "d.exr").read_bytes(), ".npy": (_ROOT / "d.npy").read_bytes()}


DEPTH = _depth_files()


@st.composite
def edited_npy(draw) -> bytes:
    """Header edits (shape, dtype, order) or bytewise damage."""
    raw = DEPTH[".npy"]
    if draw(st.booleans()):
        return draw(corrupted(raw))
    header = raw[:128].decode("latin1")  # numpy pads the 1.0 header to 128 bytes
    field = draw(st.sampled_from(["shape", "descr", "fortran"]))
    new = {"shape": draw(st.sampled_from(["(12, 10)", "(4294967296, 10)", "(99999999999999999999,)", "(-1, 10)",
                                          "(12, 10, 1)", "()", "(0,)", "'x'"])),
           "descr": draw(st.sampled_from(["'<f8'", "'|O'", "'<c8'", "'>f4'", "'<M8[s]'", "'V4'", "'<f4'", "12"])),
           "fortran": draw(st.sampled_from(["True", "None", "1"]))}[field]
    key = {"shape": "'shape': ", "descr": "'descr': ", "fortran": "'fortran_order': "}[field]
    start = header.index(key) + len(key)
    end = header.index("), " if field == "shape" else ", ", start) + (1 if field == "shape" else 0)
    edited = header[:start] + new + header[end:]
    edited = edited[:-1].ljust(127)[:127] + "\n"  # keep the header length numpy recorded
    return edited.encode("latin1") + raw[128:]


@FUZZ
@given(st.one_of(corrupted(DEPTH[".exr"]).map(lambda b: (".exr", b)), edited_npy().map(lambda b: (".npy", b))))
def test_corrupted_depth_files(case):
    suffix, raw = case
    with scratch() as d, no_hang():
        path = d / f"depth{suffix}"
        path.write_bytes(raw)
        try:
            values, valid, _ = read_depth_file(path)
        except Exception as exc:  # noqa: BLE001
            assert_names(exc, path)
        else:
            assert values.ndim == 2 and values.dtype == np.float32
            assert valid is None or valid.shape == values.shape


def test_npy_with_a_huge_shape_is_not_allocated():
    """np.load allocates the shape its header declares; the reader memory-maps first, so 2^32 x 10 float32
    (160 GiB) in a 1 kB file is an error naming the file, not a MemoryError."""
    with scratch() as d:
        path = d / "big.npy"
        with open(path, "wb") as f:
            np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": (2**32, 10)})
            f.write(np.ones(120, np.float32).tobytes())
        with pytest.raises(SceneError) as exc:
            read_depth_file(path)
    assert str(path) in str(exc.value)
