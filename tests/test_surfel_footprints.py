"""Surfel tile footprints (kernels/surfel_project.py surfel_footprints): every pixel a surfel can reach lies in its
tile rectangle, also for disks that reach the camera plane, whose footprint bounds the image of the part of the disk
in front of the near plane and on the screen (not the whole screen), close to the tightest rectangle; renders of
such surfels match the float64 reference."""
import numpy as np
import torch
import warp as wp

from reference_surfels import (ALL_OUTPUTS, quat_from_normal, random_surfel_scene, render_surfels_ref,
                               surfel_transforms)
from warpgs import rasterize_surfels
from warpgs.kernels import surfel_project

W, H, TILE, NEAR = 64, 48, 8, 0.01
FILTER_INV = 2.0  # screen-space fallback sigma 1/sqrt(2) px


def near_camera_surfels(n, seed):
    """Transforms (reference_surfels.surfel_transforms, camera at the origin), projected centres and opacities of
    surfels close to the camera, most of whose 3-sigma disks reach its plane."""
    rng = np.random.default_rng(seed)
    centres = np.concatenate([rng.normal(0.0, 0.3, (n, 2)), rng.uniform(0.011, 0.3, (n, 1))], 1)
    K = torch.tensor([[50.0, 0.0, W / 2], [0.0, 50.0, H / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    M = surfel_transforms(torch.from_numpy(centres), torch.from_numpy(rng.normal(size=(n, 4))),
                          torch.from_numpy(rng.uniform(0.02, 0.5, (n, 2))), torch.eye(4, dtype=torch.float64), K)
    M = M.numpy().astype(np.float32)
    means2d = (M[:, :2, 2] / M[:, 2:, 2]).astype(np.float32)
    return M, means2d, rng.uniform(0.05, 0.99, n).astype(np.float32)


def footprints(M, means2d, opacities):
    n = len(M)
    rects = wp.zeros(n, dtype=wp.vec4i, device="cpu")
    counts = wp.zeros(n, dtype=wp.int32, device="cpu")
    q_cut = wp.zeros(n, dtype=float, device="cpu")
    wp.launch(surfel_project.surfel_footprints, dim=n, device="cpu",
              inputs=[wp.array(M, dtype=wp.mat33, device="cpu"), wp.array(means2d, dtype=wp.vec2, device="cpu"),
                      wp.array(opacities, dtype=float, device="cpu"), wp.ones(n, dtype=wp.int32, device="cpu"),
                      FILTER_INV, NEAR, W, H, TILE, 0.0, 1.0 / 255.0, rects, counts, q_cut])
    return rects.numpy(), counts.numpy()


def reached_pixels(M, mean2d, opacity):
    """Pixel centres (x, y) that can receive alpha >= 1/255 from the surfel, in float64: the ray meets the disk at
    u^2 + v^2 <= q (q from the opacity, as generous as the blend's cut-off) at depth >= near, or the screen-space
    fallback reaches them."""
    py, px = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    px, py = px.ravel(), py.ravel()
    M = M.astype(np.float64)
    zeta = np.cross(px[:, None] * M[2] - M[0], py[:, None] * M[2] - M[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = zeta[:, 0] / zeta[:, 2], zeta[:, 1] / zeta[:, 2]
        depth = u * M[2, 0] + v * M[2, 1] + M[2, 2]
        q = 2.0 * np.log(float(opacity) * 255.0) * 1.0001 + 1e-4
        hit = (u * u + v * v <= q) & (depth >= NEAR)
    hit |= FILTER_INV * ((px - mean2d[0]) ** 2 + (py - mean2d[1]) ** 2) <= q
    return px[hit], py[hit]


def reaches_camera_plane(M, opacity):
    rz = M[2].astype(np.float64) / M[2, 2]
    return 2.0 * np.log(float(opacity) * 255.0) * (rz[0] ** 2 + rz[1] ** 2) >= 0.99


def test_every_reached_pixel_lies_in_the_footprint_and_disks_at_the_camera_plane_do_not_take_the_whole_screen():
    M, means2d, opacities = near_camera_surfels(1500, seed=0)
    rects, counts = footprints(M, means2d, opacities)
    crossing, ours, tightest = 0, 0, 0
    for i in range(len(M)):
        x, y = reached_pixels(M[i], means2d[i], opacities[i])
        x0, y0, x1, y1 = rects[i]
        tx, ty = (x // TILE).astype(int), (y // TILE).astype(int)
        assert ((tx >= x0) & (tx <= x1) & (ty >= y0) & (ty <= y1)).all(), f"surfel {i}: a reached pixel outside"
        if reaches_camera_plane(M[i], opacities[i]):
            crossing += 1
            ours += int(counts[i])
            if len(tx):  # the smallest tile rectangle holding every reached pixel
                tightest += (tx.max() - tx.min() + 1) * (ty.max() - ty.min() + 1)
    assert crossing > 1000  # the scene is mostly such disks
    # the whole screen for each of them would be 2.2x the tightest rectangles here, the near cut alone 1.5x
    assert ours <= 1.15 * tightest


def test_renders_of_disks_reaching_the_camera_plane_match_the_reference():
    scene = random_surfel_scene(n=40, seed=11)
    R, t = scene["viewmat"][:3, :3], scene["viewmat"][:3, 3]
    eye = -R.T @ t
    gen = torch.Generator().manual_seed(3)
    for i in range(0, 40, 2):  # half the surfels a little in front of the camera, large and tilted
        offset = torch.randn(3, generator=gen, dtype=torch.float64) * torch.tensor([0.6, 0.6, 0.0], dtype=torch.float64)
        offset[2] = 0.05 + 0.4 * torch.rand(1, generator=gen, dtype=torch.float64).item()
        scene["means"][i] = eye + R.T @ offset
        scene["quats"][i] = quat_from_normal(torch.randn(3, generator=gen, dtype=torch.float64))
        scene["scales"][i] = torch.rand(2, generator=gen, dtype=torch.float64) * 0.8 + 0.2
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    out = rasterize_surfels(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], s["viewmat"], s["K"],
                            s["width"], s["height"], outputs=ALL_OUTPUTS[:-1])
    ref = render_surfels_ref(scene)
    for name in ("rgb", "alpha", "inv_depth", "normal"):  # inverse depths up to ~20 here: relative float32 rounding
        err = (getattr(out, name).double() - ref[name]).abs() - 1e-4 * ref[name].abs()
        assert err.max() <= 1e-4, name
