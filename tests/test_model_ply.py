"""PLY files in the 3DGS / 2DGS layouts: exact round trips, property order, atomic writes, clear errors."""
import os

import numpy as np
import pytest
import torch

from warpgs.model.gaussians import GaussianModel, SurfelModel, load_ply, read_ply

THREEDGS_PROPS = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                  + [f"f_rest_{i}" for i in range(45)] + ["opacity", "scale_0", "scale_1", "scale_2"]
                  + [f"rot_{i}" for i in range(4)])


def random_model(cls=GaussianModel, n=17, degree=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return cls(torch.randn(n, 3, generator=g), torch.randn(n, cls.num_scales, generator=g),
               torch.randn(n, 4, generator=g), torch.randn(n, generator=g) * 5, torch.randn(n, 1, 3, generator=g),
               torch.randn(n, k - 1, 3, generator=g))


def header(path):
    raw = open(path, "rb").read()
    return raw[: raw.index(b"end_header\n") + len(b"end_header\n")].decode().splitlines(), raw


def test_round_trip_exact(tmp_path):
    m = random_model()
    m.add_extra("language", torch.randn(17, 8))
    m.save_ply(tmp_path / "m.ply")
    back = load_ply(tmp_path / "m.ply")
    assert type(back) is GaussianModel and back.max_sh_degree == 3 and back.active_sh_degree == 3
    assert set(back.params) == set(m.params)
    for name in m.params:
        assert torch.equal(back.params[name], m.params[name]), name


@pytest.mark.parametrize("degree", [0, 1])
def test_round_trip_surfels_and_low_degree(tmp_path, degree):
    s = random_model(SurfelModel, degree=degree)
    s.save_ply(tmp_path / "s.ply")
    back = load_ply(tmp_path / "s.ply")
    assert type(back) is SurfelModel and back.max_sh_degree == degree
    assert all(torch.equal(back.params[n], s.params[n]) for n in s.params)
    lines, _ = header(tmp_path / "s.ply")
    props = [ln.split()[-1] for ln in lines if ln.startswith("property")]
    assert "scale_2" not in props and props[-6:] == ["scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"]


def test_layout_is_3dgs(tmp_path):
    m = random_model(n=5)
    m.save_ply(tmp_path / "m.ply", include_extras=False)
    lines, raw = header(tmp_path / "m.ply")
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 5"]
    assert lines[3:-1] == [f"property float {p}" for p in THREEDGS_PROPS]
    # Independent decode: 62 little-endian float32 per vertex right after the header.
    body = np.frombuffer(raw[len("\n".join(lines)) + 1:], dtype="<f4").reshape(5, 62)
    assert np.array_equal(body[:, 0:3], m.means.detach().numpy())
    assert np.array_equal(body[:, 3:6], np.zeros((5, 3), np.float32))
    # Channel-major rest coefficients: f_rest_{c*15+k} holds coefficient k of channel c.
    rest = m.shN.detach().numpy()
    for c in range(3):
        for k in range(15):
            assert np.array_equal(body[:, 9 + c * 15 + k], rest[:, k, c])
    assert np.array_equal(body[:, 54], m.logit_opacities.detach().numpy())  # logit, not sigmoid
    assert np.array_equal(body[:, 55:58], m.log_scales.detach().numpy())  # log, not exp
    assert np.array_equal(body[:, 58:62], m.quats.detach().numpy())  # wxyz


def test_overwrite_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "m.ply"
    random_model(n=3).save_ply(path)
    before = path.read_bytes()

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        random_model(n=9, seed=1).save_ply(path)
    assert path.read_bytes() == before  # the old file is intact
    assert os.listdir(tmp_path) == ["m.ply"]  # and no temp file is left behind
    monkeypatch.undo()
    random_model(n=9, seed=1).save_ply(path)
    assert load_ply(path).num_primitives == 9 and os.listdir(tmp_path) == ["m.ply"]


def write_raw(path, fmt, props, data: bytes, n, extra_elements=""):
    head = f"ply\nformat {fmt} 1.0\ncomment made by hand\n{extra_elements}element vertex {n}\n"
    head += "".join(f"property {t} {p}\n" for t, p in props) + "end_header\n"
    path.write_bytes(head.encode() + data)


def test_reads_big_endian_and_skips_other_elements(tmp_path):
    m = random_model(n=4, degree=0)
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    cols = np.concatenate([m.means.detach().numpy(), m.sh0.detach().numpy()[:, 0],
                           m.logit_opacities.detach().numpy()[:, None], m.log_scales.detach().numpy(),
                           m.quats.detach().numpy()], 1).astype(">f4")
    # A preceding element of 2 x (uchar, double) = 18 bytes must be skipped.
    write_raw(tmp_path / "b.ply", "binary_big_endian", [("float", nm) for nm in names], b"\0" * 18 + cols.tobytes(), 4,
              extra_elements="element meta 2\nproperty uchar a\nproperty double b\n")
    back = load_ply(tmp_path / "b.ply")
    assert all(torch.equal(back.params[n], m.params[n]) for n in m.params)


@pytest.mark.parametrize("fmt,props,match", [
    ("ascii", [("float", "x")], "binary"),
    ("binary_little_endian", [("float", "x"), ("float", "y"), ("float", "z")], "scale_"),
    ("binary_little_endian", [("float", n) for n in ("x", "y", "z", "scale_0", "scale_1", "scale_2")],
     r"missing PLY properties \['f_dc_0', 'f_dc_1', 'f_dc_2', 'opacity', 'rot_0'"),
    ("binary_little_endian", [("list uchar int", "vertex_indices")], "list"),
])
def test_read_errors(tmp_path, fmt, props, match):
    write_raw(tmp_path / "bad.ply", fmt, props, b"\0" * 64, 1)
    with pytest.raises(ValueError, match=match):
        load_ply(tmp_path / "bad.ply")


def test_not_a_ply_and_truncated(tmp_path):
    (tmp_path / "x.ply").write_bytes(b"hello")
    with pytest.raises(ValueError, match="not a PLY"):
        read_ply(tmp_path / "x.ply")
    random_model(n=4).save_ply(tmp_path / "t.ply")
    raw = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(raw[:-10])
    with pytest.raises(ValueError, match="truncated"):
        read_ply(tmp_path / "t.ply")
