"""Surfels initialised on a plane render that plane: depth, median depth and normal within 1e-3, and (all hits
at the same depth along each ray) no depth distortion."""
import math

import pytest
import torch

from random_scenes import intrinsics, look_at
from reference_surfels import quat_from_normal
from warpgs import rasterize_surfels

W, H = 32, 24


def plane_scene(normal, offset, flip_half):
    """8x8 overlapping surfels covering the view, lying in the plane {x : n·x = offset}."""
    n = torch.tensor(normal, dtype=torch.float64)
    n = n / n.norm()
    a = torch.linalg.cross(n, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    a = a / a.norm()
    b = torch.linalg.cross(n, a)
    g = torch.Generator().manual_seed(0)
    grid = torch.linspace(-3.0, 3.0, 8, dtype=torch.float64)
    means, quats = [], []
    for i, gu in enumerate(grid):
        for j, gv in enumerate(grid):
            means.append(offset * n + gu * a + gv * b)
            # Half of them are initialised with the normal pointing away: rendering faces it to the camera.
            nrm = -n if (flip_half and (i + j) % 2) else n
            quats.append(quat_from_normal(nrm, spin=float(torch.rand(1, generator=g)) * 2 * math.pi))
    count = len(means)
    return dict(means=torch.stack(means).float(), quats=torch.stack(quats).float(),
                scales=torch.full((count, 2), 0.65, dtype=torch.float32),
                opacities=torch.full((count,), 0.95, dtype=torch.float32),
                colors=torch.rand(count, 3, generator=g, dtype=torch.float64).float()), n


def plane_depth(viewmat, K, n, offset):
    """Camera z where each pixel's ray meets the plane (float64)."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                            indexing="ij")
    rays_cam = torch.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], torch.ones_like(xs)], -1)  # z = 1
    eye = -R.T @ t
    rays = rays_cam @ R  # world directions, camera z = 1 per unit length
    return ((offset - n @ eye) / (rays @ n))[..., None]


@pytest.mark.parametrize("normal,offset,flip_half", [
    ((0.0, 0.0, -1.0), 0.0, False),
    ((0.25, -0.35, -1.0), 0.3, True),
])
def test_plane_depth_and_normal(normal, offset, flip_half):
    scene, n = plane_scene(normal, offset, flip_half)
    viewmat = look_at((0.3, -0.2, -4.0), (0.0, 0.0, 0.0))
    K = intrinsics(W, H)
    out = rasterize_surfels(**scene, viewmat=viewmat.float(), K=K.float(), width=W, height=H,
                            outputs=("alpha", "depth", "median_depth", "normal", "distortion"))
    covered = out.alpha[..., 0] > 0.99
    assert covered.float().mean() > 0.9, "the plane should cover the view"
    truth = plane_depth(viewmat, K, n, offset)
    assert (out.depth.double() - truth)[covered].abs().max() <= 1e-3
    assert (out.median_depth.double() - truth)[covered].abs().max() <= 1e-3
    facing = n if float(n @ (-viewmat[:3, :3].T @ viewmat[:3, 3])) > offset else -n  # towards the camera
    unit = out.normal.double() / out.alpha.double().clamp_min(1e-12)
    assert (unit - facing)[covered].abs().max() <= 1e-3
    assert out.distortion[covered].abs().max() <= 1e-7
