"""TSDF fusion and marching cubes on exact depth maps of analytic surfaces (CPU, tiny)."""
from __future__ import annotations

import numpy as np
import pytest

from mesh_scenes import ring_cameras, sphere_depth, square_depth
from warpgs.mesh.clean import connected_components, remove_small_components, surface_area
from warpgs.mesh.from_model import MeshSettings, fuse_depth_maps
from warpgs.mesh.volume import Bound, Mesh, SparseTSDFVolume

CENTRE, RADIUS = np.array([0.1, -0.2, 0.3]), 0.5


@pytest.fixture(scope="module")
def sphere_mesh():
    views = ring_cameras(CENTRE, 2.0, elevations=(-60.0, -15.0, 30.0, 70.0), n_azimuth=9)  # the poles too
    frames = [(sphere_depth(K, V, CENTRE, RADIUS), None, K, V) for K, V in views]
    return fuse_depth_maps(frames, MeshSettings(voxel=0.02, trunc=0.06, radius=1.0), CENTRE, 1.0)


def test_sphere_area_position_and_orientation(sphere_mesh):
    v = sphere_mesh.vertices.astype(np.float64)
    dist = np.linalg.norm(v - CENTRE, axis=1)
    # the pixels (0.025 wide at the surface) are coarser than the voxels: nearest-pixel depth costs ~0.1 voxel
    assert np.abs(dist - RADIUS).mean() < 0.2 * 0.02
    assert np.abs(dist - RADIUS).max() < 0.02  # never a voxel off
    assert surface_area(sphere_mesh) == pytest.approx(4 * np.pi * RADIUS ** 2, rel=0.03)
    assert np.allclose(v.mean(0), CENTRE, atol=0.005)
    f = sphere_mesh.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (np.einsum("ij,ij->i", n, v[f].mean(1) - CENTRE) > 0).mean() > 0.99  # faces point outwards


def test_sphere_is_one_closed_piece(sphere_mesh):
    labels = connected_components(sphere_mesh.faces, len(sphere_mesh.vertices))
    assert len(np.unique(labels[sphere_mesh.faces[:, 0]])) == 1
    f = np.sort(sphere_mesh.faces, axis=1)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [0, 2]]])
    _, uses = np.unique(edges, axis=0, return_counts=True)
    # nearly watertight: an edge of one face is a hole where no view saw every corner of a cell
    assert (uses == 1).mean() < 0.002 and (uses <= 2).all()


def test_plane_area_and_height():
    height, half, voxel = 0.2, 0.6, 0.025
    views = ring_cameras((0.0, 0.0, height), 2.0, elevations=(35.0, 60.0), n_azimuth=8)
    frames = [(square_depth(K, V, height, half), None, K, V) for K, V in views]
    mesh = fuse_depth_maps(frames, MeshSettings(voxel=voxel, trunc=3 * voxel, radius=1.0, depth_trunc=10.0),
                           np.array([0.0, 0.0, height]), 1.0)
    v = mesh.vertices.astype(np.float64)
    # depth interpolated in inverse depth is exact on a plane: only the square's border is off (nearest pixel)
    inner = np.abs(v[:, :2]).max(1) < half - 2 * voxel
    assert np.median(np.abs(v[inner, 2] - height)) < 1e-3 * voxel
    assert np.abs(v[inner, 2] - height).max() < 0.15 * voxel
    assert np.abs(v[:, 2] - height).max() < 0.5 * voxel
    # the square's border is where the surface stops: marching cubes ends it within a voxel
    assert np.abs(v[:, :2]).max() == pytest.approx(half, abs=voxel)
    assert surface_area(mesh) == pytest.approx((2 * half) ** 2, rel=0.05)


def test_colour_comes_from_the_images():
    views = ring_cameras(CENTRE, 2.0, elevations=(20.0,), n_azimuth=6)
    color = np.zeros((48, 64, 3), np.float32)
    color[..., 0] = 0.8
    frames = [(sphere_depth(K, V, CENTRE, RADIUS), color, K, V) for K, V in views]
    mesh = fuse_depth_maps(frames, MeshSettings(voxel=0.04, radius=1.0), CENTRE, 1.0)
    assert len(mesh.faces) > 100
    assert np.allclose(mesh.colors, [0.8, 0.0, 0.0], atol=1e-4)


def test_volume_grows_its_table_and_pool():
    vol = SparseTSDFVolume(Bound(CENTRE, 1.0), voxel=0.02, trunc=0.06, initial_blocks=4)
    for K, V in ring_cameras(CENTRE, 2.0, elevations=(10.0,), n_azimuth=4):
        vol.integrate(sphere_depth(K, V, CENTRE, RADIUS), K, V)
    small = SparseTSDFVolume(Bound(CENTRE, 1.0), voxel=0.02, trunc=0.06, initial_blocks=1 << 12)
    for K, V in ring_cameras(CENTRE, 2.0, elevations=(10.0,), n_azimuth=4):
        small.integrate(sphere_depth(K, V, CENTRE, RADIUS), K, V)
    assert vol.num_blocks == small.num_blocks > 4
    a, b = vol.extract_mesh(), small.extract_mesh()
    assert len(a.faces) == len(b.faces) > 0
    assert surface_area(a) == pytest.approx(surface_area(b), rel=1e-5)


def test_nothing_outside_the_bound_and_depth_limits():
    views = ring_cameras(CENTRE, 2.0, elevations=(10.0,), n_azimuth=4)
    # a bound that misses the sphere allocates nothing
    far = SparseTSDFVolume(Bound(CENTRE + 5.0, 1.0), voxel=0.05, trunc=0.15)
    # depth_max before the sphere: nothing either
    near = SparseTSDFVolume(Bound(CENTRE, 1.0), voxel=0.05, trunc=0.15, depth_max=1.0)
    for K, V in views:
        d = sphere_depth(K, V, CENTRE, RADIUS)
        assert far.integrate(d, K, V) == 0 and near.integrate(d, K, V) == 0
    assert len(far.extract_mesh().faces) == 0


def test_unbounded_contracts_the_background():
    """A sphere far outside the radius is still meshed with --unbounded, coarser but in the right place."""
    far_centre, r = np.array([2.5, 0.0, 0.0]), 0.6  # grid |x| 1.9 .. 3.1, contracted to 1.47 .. 1.68
    views = ring_cameras(far_centre, 2.0, elevations=(0.0, 40.0), n_azimuth=8)
    frames = [(sphere_depth(K, V, far_centre, r), None, K, V) for K, V in views]
    mesh = fuse_depth_maps(frames, MeshSettings(voxel=0.02, radius=1.0, unbounded=True), np.zeros(3), 1.0)
    assert len(mesh.faces) > 200
    dist = np.linalg.norm(mesh.vertices - far_centre, axis=1)
    # a voxel there is 0.02 x (1.9 .. 3.1)^2 = 0.07 .. 0.19 radially: errors of half that are expected
    assert np.median(np.abs(dist - r)) < 0.1
    assert np.linalg.norm(np.median(mesh.vertices, axis=0) - far_centre) < 0.2
    bounded = fuse_depth_maps(frames, MeshSettings(voxel=0.02, radius=1.0), np.zeros(3), 1.0)
    assert len(bounded.faces) == 0


def test_small_pieces_are_dropped():
    tri = np.array([[0, 1, 2]], np.int32)
    big = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4]], np.int32) + 3
    mesh = Mesh(np.random.default_rng(0).random((9, 3)).astype(np.float32), np.concatenate([tri, big]),
                np.zeros((9, 3), np.float32))
    kept = remove_small_components(mesh, min_fraction=0.5)
    assert len(kept.faces) == 4 and len(kept.vertices) == 6
    assert np.allclose(kept.vertices, mesh.vertices[3:])
    assert len(remove_small_components(mesh, min_fraction=0.0).faces) == 5


@pytest.mark.parametrize("kwargs, message", [
    (dict(voxel=0.0, trunc=0.1), "voxel"), (dict(voxel=-1.0, trunc=0.1), "voxel"),
    (dict(voxel=0.1, trunc=float("nan")), "trunc"), (dict(voxel=0.1, trunc=0.1, depth_max=0.0), "depth"),
])
def test_bad_volume_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SparseTSDFVolume(Bound(np.zeros(3), 1.0), **kwargs)


def test_bad_depth_map_shape():
    vol = SparseTSDFVolume(Bound(np.zeros(3), 1.0), voxel=0.1, trunc=0.3)
    K, V = ring_cameras(np.zeros(3), 2.0, n_azimuth=1)[0]
    with pytest.raises(ValueError, match="depth"):
        vol.integrate(np.ones((2, 3, 4)), K, V)
    with pytest.raises(ValueError, match="color"):
        vol.integrate(np.ones((4, 5)), K, V, np.ones((4, 5, 1)))
