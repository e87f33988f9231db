"""benchmarks/silhouette_shell.py: exact surfels on a sphere against its true coverage. The disks must face the
sphere's normals, an exact shell without the screen-space fallback must draw the silhouette where it is, and with
2DGS's fallback the silhouette must come out wider (the bias docs/mesh.md explains), so the scan finds it."""
import sys
from pathlib import Path

import numpy as np
import torch

from warpgs.data.formats import raytrace
from warpgs.data.formats.synthetic import TARGET, RigSettings, orbit_rig
from warpgs.model.primitive_math import quat_to_rotmat

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import silhouette_shell as ss  # noqa: E402


def test_disks_are_tangent_to_the_sphere():
    dirs = ss.fibonacci_directions(200)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert abs(dirs.mean(0)).max() < 0.02  # spread over the whole sphere
    normals = quat_to_rotmat(torch.tensor(ss.quats_facing(dirs))).numpy()[:, :, 2]
    assert np.allclose(np.abs((normals * dirs).sum(1)), 1.0, atol=1e-9)
    disks = ss.shell(0.4, 0.05, 1.0)
    radii = (disks["means"].double() - torch.tensor(TARGET)).norm(dim=1)
    assert torch.allclose(radii, torch.full_like(radii, 0.4), atol=1e-6)


def test_the_fallback_widens_the_silhouette_of_an_exact_shell():
    cams, train, _ = orbit_rig(RigSettings(width=64, height=48))
    cams = [cams[i] for i in train][::8]
    sphere = raytrace.Sphere("sphere", tuple(TARGET), ss.RADIUS, lambda p: np.ones_like(p))
    coverage = [torch.tensor(ss.true_coverage(sphere, c)) for c in cams]
    assert all(0.0 < float(c.sum()) < c.numel() for c in coverage)
    disks = ss.shell(ss.RADIUS, 0.03, 1.0)
    err_narrow, surplus_narrow = ss.alpha_errors(disks, cams, coverage, screen_sigma=0.05)
    err_2dgs, surplus_2dgs = ss.alpha_errors(disks, cams, coverage, screen_sigma=0.5 ** 0.5)
    perimeter = 2 * np.pi * float(coverage[0].sum() / np.pi) ** 0.5  # pixels, from the covered area
    # 64x48, 4 views: 0.24 px wide without the fallback (the disks' own tails), 2.2 px with 2DGS's
    assert abs(surplus_narrow) / perimeter < 0.5
    assert surplus_2dgs / perimeter > 1.0 and err_2dgs > 3 * err_narrow
