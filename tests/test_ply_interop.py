"""PLY interop with the 3DGS ecosystem, checked with an independent reader and writer (plyfile, which the 3DGS
reference code itself uses): our point_cloud.ply reads back with the 3DGS property names, order and values,
and a file written the way 3DGS's GaussianModel.save_ply writes it loads with our reader and renders like the
float64 reference renders the same Gaussians."""
import math

import numpy as np
import pytest
import torch

from reference import render_reference
from random_scenes import intrinsics, look_at
from warpgs.model.gaussians import GaussianModel, load_ply
from warpgs.model.rendering import render_model

plyfile = pytest.importorskip("plyfile", reason="plyfile is in the test extra: pip install 'warpgs[test]'")

THREEDGS_DEGREE3 = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                    + [f"f_rest_{i}" for i in range(45)] + ["opacity", "scale_0", "scale_1", "scale_2"]
                    + [f"rot_{i}" for i in range(4)])


def threedgs_attributes(num_rest_coeffs: int) -> list:
    """GaussianModel.construct_list_of_attributes of the 3DGS reference code, for 3 scales and 4 rotations."""
    names = ["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
    names += [f"f_rest_{i}" for i in range(3 * num_rest_coeffs)]
    return names + ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]


def test_our_ply_reads_back_with_plyfile_in_3dgs_layout(tmp_path):
    g = torch.Generator().manual_seed(0)
    n = 9
    model = GaussianModel(torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g),
                          torch.randn(n, generator=g), torch.randn(n, 1, 3, generator=g), torch.randn(n, 15, 3, generator=g))
    model.save_ply(tmp_path / "point_cloud.ply", include_extras=False)

    ply = plyfile.PlyData.read(str(tmp_path / "point_cloud.ply"))
    assert not ply.text and ply.byte_order == "<"  # binary_little_endian, as 3DGS writes and viewers expect
    assert [e.name for e in ply.elements] == ["vertex"]
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == THREEDGS_DEGREE3 == threedgs_attributes(15)
    assert all(vertex[p.name].dtype == np.float32 for p in vertex.properties)
    assert vertex.count == n
    col = lambda name: torch.from_numpy(np.asarray(vertex[name]).copy())  # noqa: E731
    assert torch.equal(torch.stack([col(a) for a in "xyz"], 1), model.means.detach())
    assert all(torch.equal(col(a), torch.zeros(n)) for a in ("nx", "ny", "nz"))
    assert torch.equal(torch.stack([col(f"f_dc_{c}") for c in range(3)], 1), model.sh0.detach()[:, 0])
    # f_rest is channel-major (3DGS: features_rest.transpose(1, 2).flatten(1)): coefficient k of channel c at c*15+k.
    rest = torch.stack([col(f"f_rest_{i}") for i in range(45)], 1).reshape(n, 3, 15).transpose(1, 2)
    assert torch.equal(rest, model.shN.detach())
    assert torch.equal(col("opacity"), model.logit_opacities.detach())  # pre-activation, as 3DGS stores it
    assert torch.equal(torch.stack([col(f"scale_{i}") for i in range(3)], 1), model.log_scales.detach())
    assert torch.equal(torch.stack([col(f"rot_{i}") for i in range(4)], 1), model.quats.detach())  # wxyz


def write_like_3dgs(path, xyz, features_dc, features_rest, opacity, scaling, rotation):
    """3DGS's GaussianModel.save_ply, step for step: features [N, K, 3] transposed to channel-major and
    flattened, the attributes concatenated in construct_list_of_attributes order, one PlyElement 'vertex',
    written by plyfile (binary, little endian on the machines 3DGS runs on; said explicitly here)."""
    normals = np.zeros_like(xyz)
    f_dc = features_dc.transpose(0, 2, 1).reshape(len(xyz), -1)
    f_rest = features_rest.transpose(0, 2, 1).reshape(len(xyz), -1)
    dtype_full = [(attribute, "f4") for attribute in threedgs_attributes(features_rest.shape[1])]
    elements = np.empty(xyz.shape[0], dtype=dtype_full)
    attributes = np.concatenate((xyz, normals, f_dc, f_rest, opacity, scaling, rotation), axis=1)
    elements[:] = list(map(tuple, attributes))
    el = plyfile.PlyElement.describe(elements, "vertex")
    plyfile.PlyData([el], byte_order="<").write(str(path))


def test_a_3dgs_written_ply_loads_and_renders(tmp_path):
    rng = np.random.default_rng(1)
    n, width, height = 40, 48, 36
    # A blob of Gaussians in front of the camera, in 3DGS's stored (pre-activation) parameterisation.
    xyz = (rng.normal(size=(n, 3)) * [0.6, 0.45, 0.3]).astype(np.float32)
    features_dc = (rng.normal(size=(n, 1, 3)) * 0.8).astype(np.float32)
    features_rest = (rng.normal(size=(n, 15, 3)) * 0.15).astype(np.float32)
    opacity = rng.normal(0.5, 1.0, size=(n, 1)).astype(np.float32)  # logits
    scaling = np.log(rng.uniform(0.05, 0.25, size=(n, 3))).astype(np.float32)  # log scales
    rotation = rng.normal(size=(n, 4)).astype(np.float32)  # unnormalised wxyz
    write_like_3dgs(tmp_path / "point_cloud.ply", xyz, features_dc, features_rest, opacity, scaling, rotation)

    model = load_ply(tmp_path / "point_cloud.ply")
    assert type(model) is GaussianModel and model.num_primitives == n
    assert model.max_sh_degree == 3 and model.active_sh_degree == 3  # every band of the file is used
    assert torch.equal(model.means.detach(), torch.from_numpy(xyz))
    assert torch.equal(model.shN.detach(), torch.from_numpy(features_rest))
    assert torch.equal(model.logit_opacities.detach(), torch.from_numpy(opacity[:, 0]))

    viewmat = look_at((0.4, -0.3, -3.5), (0.0, 0.0, 0.0))
    K = intrinsics(width, height, fov_x_deg=50.0)
    background = torch.tensor([0.1, 0.2, 0.3])
    with torch.no_grad():
        out = render_model(model, viewmat.float(), K.float(), width, height, outputs=("rgb", "alpha"),
                           background=background)
    assert out.rgb.shape == (height, width, 3) and torch.isfinite(out.rgb).all()
    assert out.alpha.max() > 0.9 and out.alpha.min() < 0.05  # the blob covers the middle, not the corners
    assert (out.rgb >= 0).all() and out.rgb.std() > 0.02  # coloured, not a flat fill

    # The same Gaussians through the float64 reference, activated the 3DGS way from the raw arrays.
    t = lambda a: torch.from_numpy(np.asarray(a, np.float64))  # noqa: E731
    sh = torch.cat([t(features_dc), t(features_rest)], 1)
    ref = render_reference(t(xyz), t(rotation), t(scaling).exp(), torch.sigmoid(t(opacity[:, 0])), sh, viewmat, K,
                           width, height, sh_degree=3, background=background.double())
    assert (out.rgb.double() - ref["rgb"]).abs().max() < 1e-4
    assert (out.alpha.double() - ref["alpha"]).abs().max() < 1e-4
    assert math.isclose(out.alpha.mean().item(), ref["alpha"].mean().item(), abs_tol=1e-5)
