"""warpgs-mesh end to end on a tiny trained run, its argument errors, and the PLY it writes (read back with
plyfile, as Blender/MeshLab/Open3D importers read it)."""
from __future__ import annotations

import numpy as np
import pytest

from train_fixtures import quick_overrides
from warpgs.mesh.cli import main
from warpgs.mesh.ply_mesh import write_mesh_ply
from warpgs.mesh.volume import Mesh

plyfile = pytest.importorskip("plyfile")


@pytest.fixture(scope="module")
def surfel_run(tmp_path_factory):
    from warpgs.cli.commands import train_main

    out = tmp_path_factory.mktemp("surfel_run")
    assert train_main(["--quiet"] + quick_overrides(out, steps=5, **{"model.kind": "surfels"})) == 0
    return out


def test_mesh_of_a_trained_run(surfel_run, tmp_path, capsys):
    out = tmp_path / "mesh.ply"
    assert main(["--model", str(surfel_run), "--voxel", "0.1", "--radius", "2", "--out", str(out)]) == 0
    assert "faces" in capsys.readouterr().out
    ply = plyfile.PlyData.read(str(out))
    v, f = ply["vertex"], ply["face"]
    assert len(v) > 0 and len(f) > 0
    faces = np.stack(f["vertex_indices"])
    assert faces.shape[1] == 3 and faces.min() >= 0 and faces.max() < len(v)
    xyz = np.stack([v["x"], v["y"], v["z"]], 1)
    assert np.isfinite(xyz).all()
    normals = np.stack([v["nx"], v["ny"], v["nz"]], 1)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-3)


def test_gaussians_mesh_from_expected_depth(tmp_path, capsys):
    from warpgs.cli.commands import train_main

    run = tmp_path / "gaussian_run"
    assert train_main(["--quiet"] + quick_overrides(run, steps=3, **{"model.kind": "gaussians"})) == 0
    capsys.readouterr()
    assert main(["--model", str(run), "--voxel", "0.1", "--radius", "2"]) == 0
    assert "expected depth" in capsys.readouterr().err
    assert len(plyfile.PlyData.read(str(run / "mesh.ply"))["face"]) > 0
    # 3D Gaussians have no median depth to fuse: the flag is named, and no file is written
    assert main(["--model", str(run), "--voxel", "0.1", "--radius", "2", "--depth", "median",
                 "--out", str(tmp_path / "median.ply")]) != 0
    assert "--depth median" in capsys.readouterr().err and not (tmp_path / "median.ply").exists()


def test_surfels_mesh_from_either_depth(surfel_run, tmp_path):
    """--depth picks the rendered depth fused (median by default for surfels): both mesh; the two differ."""
    meshes = {}
    for depth in ("median", "expected"):
        out = tmp_path / f"{depth}.ply"
        assert main(["--model", str(surfel_run), "--voxel", "0.1", "--radius", "2", "--depth", depth,
                     "--out", str(out)]) == 0
        v = plyfile.PlyData.read(str(out))["vertex"]
        meshes[depth] = np.stack([v["x"], v["y"], v["z"]], 1)
    assert len(meshes["median"]) > 0 and len(meshes["expected"]) > 0
    assert meshes["median"].shape != meshes["expected"].shape or not np.allclose(meshes["median"], meshes["expected"])


def test_ply_round_trip(tmp_path):
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
    colors = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0.5]], np.float32)
    path = tmp_path / "tet.ply"
    write_mesh_ply(path, Mesh(verts, faces, colors), comment="a tetrahedron")
    ply = plyfile.PlyData.read(str(path))
    assert ply.text is False and ply.byte_order == "<"
    v = ply["vertex"]
    assert np.array_equal(np.stack([v["x"], v["y"], v["z"]], 1), verts)
    assert np.array_equal(np.stack([v["red"], v["green"], v["blue"]], 1),
                          np.round(colors * 255).astype(np.uint8))
    assert np.array_equal(np.stack(ply["face"]["vertex_indices"]), faces)
    n = np.stack([v["nx"], v["ny"], v["nz"]], 1)
    assert np.dot(n[0], [-1, -1, -1]) / np.sqrt(3) > 0.99  # outward at the corner at the origin
    assert any("tetrahedron" in c for c in ply.comments)


def test_ply_comment_with_non_ascii_characters(tmp_path):
    """The comment names the run folder, which may be any name; the PLY header must stay ASCII."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    path = tmp_path / "tri.ply"
    write_mesh_ply(path, Mesh(verts, np.array([[0, 1, 2]], np.int32), np.zeros((3, 3), np.float32)),
                   comment="warpgs-mesh of café: surfels")
    ply = plyfile.PlyData.read(str(path))
    assert len(ply["face"]) == 1 and any("caf" in c and "surfels" in c for c in ply.comments)


def test_unwritable_output_names_the_argument(surfel_run, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    assert main(["--model", str(surfel_run), "--voxel", "0.1", "--radius", "2",
                 "--out", str(blocker / "mesh.ply")]) == 2
    assert "--out: cannot write" in capsys.readouterr().err


def _error_of(argv, capsys) -> str:
    assert main(argv) == 2
    return capsys.readouterr().err


def test_missing_run_folder(tmp_path, capsys):
    err = _error_of(["--model", str(tmp_path / "nowhere")], capsys)
    assert "--model" in err and "nowhere" in err


def test_folder_that_is_not_a_run(tmp_path, capsys):
    assert "config.yaml" in _error_of(["--model", str(tmp_path)], capsys)


@pytest.mark.parametrize("flag, value", [("--voxel", "0"), ("--voxel", "-0.1"), ("--trunc", "0"),
                                         ("--depth-trunc", "-1"), ("--radius", "nan")])
def test_non_positive_lengths(tmp_path, capsys, flag, value):
    err = _error_of(["--model", str(tmp_path), flag, value], capsys)
    assert flag in err and "positive" in err


def test_bad_output_name_and_centre(tmp_path, capsys):
    assert ".ply" in _error_of(["--model", str(tmp_path), "--out", str(tmp_path / "mesh.obj")], capsys)
    with pytest.raises(SystemExit):
        main(["--model", str(tmp_path), "--center", "1,2"])
    assert "x,y,z" in capsys.readouterr().err
