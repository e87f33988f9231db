"""The surfel oracle: a float64, brute-force, pure-torch 2D Gaussian surfel (2DGS) renderer written for
obviousness, not speed.

Every surfel is intersected with every pixel's ray; no tiles, no footprints. Blending is an explicit
front-to-back loop with the same rules as the Warp renderer: exact ray-splat hit through the homogeneous
transform, screen-space fallback exp(-|pixel - centre|^2 / (2 sigma^2)) (2DGS: sigma 1/sqrt(2) px) for splats seen
edge-on, alpha = min(alpha_max, o G), skip alpha < 1/255, stop before T < 1e-4. The distortion is written as the plain pairwise sum.

At the bottom: random surfel scenes for the tests.
"""
import math
import os

import torch

from random_scenes import intrinsics, look_at
from reference import quat_to_rotation, sh_to_rgb

DIST_NEAR, DIST_FAR = 0.2, 100.0  # 2DGS's fixed NDC planes for the distortion term
ALL_OUTPUTS = ("rgb", "alpha", "depth", "inv_depth", "normal", "median_depth", "distortion", "features")
CHANNELS = {"rgb": 3, "alpha": 1, "depth": 1, "inv_depth": 1, "normal": 3, "median_depth": 1, "distortion": 1}
# The suite runs on the CPU (CI); WARPGS_TEST_DEVICE=cuda runs the Warp side of it on a GPU instead.
DEVICE = os.environ.get("WARPGS_TEST_DEVICE", "cpu")


def surfel_transforms(means, quats, scales, viewmat, K):
    """[N,3,3] matrices taking disk coordinates (u, v, 1) to homogeneous pixels (x z, y z, z)."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    Kf = torch.zeros(3, 3, dtype=means.dtype, device=means.device)  # skew is ignored, as in the op
    Kf[0, 0], Kf[1, 1], Kf[0, 2], Kf[1, 2], Kf[2, 2] = K[0, 0], K[1, 1], K[0, 2], K[1, 2], 1.0
    Rq = quat_to_rotation(quats)
    s = torch.clamp(scales, -1e8, 1e8)
    axis_u = Rq[:, :, 0] * s[:, :1]  # world-space disk axes, scaled
    axis_v = Rq[:, :, 1] * s[:, 1:]
    centre = means @ R.T + t
    columns = torch.stack([axis_u @ R.T, axis_v @ R.T, centre], -1)  # [N,3,3] camera space, columns
    return Kf @ columns


def render_surfels_reference(means, quats, scales, opacities, colors, viewmat, K, width, height, *,
                             sh_degree=None, features=None, background=None, near=0.01, far=1e10, pixels=None,
                             alpha_min=1.0 / 255.0, transmittance_min=1e-4, alpha_max=0.99,
                             screen_sigma=0.5 ** 0.5):
    """Returns a dict of [H,W,C] float64 images: rgb, alpha, depth, inv_depth, normal, median_depth,
    distortion and (if given) features. pixels: optional [P,2] (x, y) indices; then values are [P,C]."""
    dtype, device = means.dtype, means.device
    n = means.shape[0]
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    p = means @ R.T + t
    zc = p[:, 2]
    valid = (zc >= near) & (zc <= far)
    zs = torch.clamp(zc, min=near)
    mean2d = torch.stack([fx * p[:, 0] / zs + cx, fy * p[:, 1] / zs + cy], -1)
    M = surfel_transforms(means, quats, scales, viewmat, K)

    campos = -R.T @ t
    normal = quat_to_rotation(quats)[:, :, 2]
    facing_away = ((normal * (means - campos)).sum(-1) > 0).detach()
    normal = torch.where(facing_away[:, None], -normal, normal)
    if sh_degree is None:
        rgb = colors
    else:
        d = means - campos
        d = d / torch.sqrt(torch.clamp((d * d).sum(-1, keepdim=True), min=1e-24))
        rgb = sh_to_rgb(colors, sh_degree, d)

    if pixels is None:
        ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype, device=device),
                                torch.arange(width, dtype=dtype, device=device), indexing="ij")
        pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1) + 0.5
    else:
        pix = pixels.to(dtype) + 0.5
    px, py = pix[:, 0, None, None], pix[:, 1, None, None]  # [P,1,1]

    # The pixel's ray is where the planes x = px and y = py meet; in disk coordinates both are lines.
    h_u = px * M[None, :, 2, :] - M[None, :, 0, :]  # [P,N,3]
    h_v = py * M[None, :, 2, :] - M[None, :, 1, :]
    zeta = torch.linalg.cross(h_u, h_v)
    ok = zeta[..., 2] != 0
    denom = torch.where(ok, zeta[..., 2], torch.ones_like(zeta[..., 2]))
    u = torch.where(ok, zeta[..., 0] / denom, torch.zeros_like(denom))
    v = torch.where(ok, zeta[..., 1] / denom, torch.zeros_like(denom))
    s3 = u * u + v * v
    z_hit = u * M[None, :, 2, 0] + v * M[None, :, 2, 1] + M[None, :, 2, 2]
    hit = (ok & (s3 < 1e30) & (z_hit >= near)).detach()

    s2 = ((pix[:, None, :] - mean2d[None, :, :]) ** 2).sum(-1) / screen_sigma ** 2  # screen-space Gaussian
    use_hit = (hit & (s3 <= s2)).detach()
    s = torch.where(use_hit, s3, s2)
    z = torch.where(use_hit, z_hit, zs[None, :].expand_as(s2))
    alpha = torch.clamp(opacities[None, :] * torch.exp(-0.5 * s), max=alpha_max)
    blends = (valid[None, :] & (alpha >= alpha_min)).detach()

    order = torch.argsort(torch.where(valid, zc, torch.full_like(zc, math.inf)).detach(), stable=True)
    P = pix.shape[0]
    T = torch.ones(P, dtype=dtype, device=device)
    stopped = torch.zeros(P, dtype=torch.bool, device=device)
    median = torch.zeros(P, dtype=dtype, device=device)
    weights, depths = [], []
    for i in order.tolist():
        a = alpha[:, i]
        candidate = blends[:, i] & ~stopped
        next_T = T * (1.0 - a)
        stop = candidate & (next_T < transmittance_min).detach()
        stopped = stopped | stop
        take = candidate & ~stop
        weights.append(torch.where(take, a * T, torch.zeros_like(a)))
        depths.append(z[:, i])
        median = torch.where(take & (T > 0.5).detach(), z[:, i], median)
        T = torch.where(take, next_T, T)
    w = torch.stack(weights, 1) if n else torch.zeros(P, 0, dtype=dtype, device=device)  # [P,N] sorted order
    zo = torch.stack(depths, 1) if n else torch.zeros(P, 0, dtype=dtype, device=device)

    out = {"alpha": (1.0 - T)[:, None]}
    out["rgb"] = w @ rgb[order] + (T[:, None] * background[None, :] if background is not None else 0.0)
    out["depth"] = (w * zo).sum(1, keepdim=True) / torch.clamp(out["alpha"], min=1e-10)
    out["inv_depth"] = (w / zo).sum(1, keepdim=True)
    out["normal"] = w @ normal[order]
    out["median_depth"] = median[:, None]
    ndc = DIST_FAR / (DIST_FAR - DIST_NEAR) * (1.0 - DIST_NEAR / zo)  # 2DGS's mapped depth
    pairwise = w[:, :, None] * w[:, None, :] * (ndc[:, :, None] - ndc[:, None, :]) ** 2
    out["distortion"] = 0.5 * pairwise.sum((1, 2))[:, None]  # Σ_{i<j} w_i w_j (m_i - m_j)^2
    if features is not None:
        out["features"] = w @ features[order]
    if pixels is not None:
        return out
    return {k: v.reshape(height, width, -1) for k, v in out.items()}


# ---- test scenes -------------------------------------------------------------------------------------------

def quat_from_normal(nrm, spin=0.0):
    """wxyz quaternion whose rotation has third column `nrm` (unit) and an arbitrary spin about it."""
    nrm = nrm / nrm.norm()
    helper = torch.tensor([1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0], dtype=nrm.dtype)
    a = torch.linalg.cross(helper, nrm)
    a = a / a.norm()
    b = torch.linalg.cross(nrm, a)
    a, b = math.cos(spin) * a + math.sin(spin) * b, -math.sin(spin) * a + math.cos(spin) * b
    Rm = torch.stack([a, b, nrm], 1)
    w = torch.sqrt(torch.clamp(1 + Rm.trace(), min=1e-12)) / 2
    if w < 1e-3:  # 180-degree rotations: use the largest diagonal branch
        i = int(torch.argmax(torch.diagonal(Rm)))
        j, k = (i + 1) % 3, (i + 2) % 3
        r = torch.sqrt(1 + Rm[i, i] - Rm[j, j] - Rm[k, k])
        q = torch.zeros(4, dtype=nrm.dtype)
        q[0] = (Rm[k, j] - Rm[j, k]) / (2 * r)
        q[1 + i] = r / 2
        q[1 + j] = (Rm[j, i] + Rm[i, j]) / (2 * r)
        q[1 + k] = (Rm[k, i] + Rm[i, k]) / (2 * r)
        return q
    return torch.stack([w, (Rm[2, 1] - Rm[1, 2]) / (4 * w), (Rm[0, 2] - Rm[2, 0]) / (4 * w),
                        (Rm[1, 0] - Rm[0, 1]) / (4 * w)])


def random_surfel_scene(n=48, width=32, height=24, seed=0, sh_degree=None, num_features=0):
    """A dict of float64 tensors (scales [N,2]) and sizes: overlapping, tilted, back-facing, nearly edge-on,
    off-screen and behind-camera surfels seen by a rotated, translated camera."""
    g = torch.Generator().manual_seed(seed)
    eye = torch.tensor([0.3, -0.2, -4.0], dtype=torch.float64)
    viewmat = look_at(tuple(eye.tolist()), (0.0, 0.0, 0.0))
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([1.1, 0.8, 1.0], dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    if n >= 10:
        means[0] = torch.tensor([0.3, -0.2, -6.0])  # behind the camera
        means[1] = torch.tensor([8.0, 0.0, 0.0])  # off-screen
        means[2] = torch.tensor([2.0, 0.0, 0.0])  # centre off-screen, disk partly on-screen
        means[3:6] = torch.tensor([[0.0, 0.0, -0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.5]])  # stack on one ray
        view_dir = means[6] - eye
        side = torch.linalg.cross(view_dir, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
        quats[6] = quat_from_normal(side + 0.15 * view_dir / view_dir.norm() * side.norm())  # nearly edge-on
        quats[7] = quat_from_normal(means[7] - eye)  # normal points away from the camera (back-facing)
    scales = torch.rand(n, 2, generator=g, dtype=torch.float64) * 0.4 + 0.04
    opacities = torch.rand(n, generator=g, dtype=torch.float64) * 0.95 + 0.02
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    else:
        colors = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.4
    features = torch.randn(n, num_features, generator=g, dtype=torch.float64) if num_features else None
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmat=viewmat,
                K=intrinsics(width, height), features=features, width=width, height=height, sh_degree=sh_degree)


def render_surfels_ours(scene, outputs, background=None, **kw):
    """The Warp op on the scene (float32) on DEVICE; images come back on the CPU."""
    from warpgs import rasterize_surfels

    s = {k: (v.float().to(DEVICE) if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    out = rasterize_surfels(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], s["viewmat"], s["K"],
                            s["width"], s["height"], sh_degree=s["sh_degree"], features=s["features"],
                            background=None if background is None else background.float().to(DEVICE),
                            outputs=outputs, **kw)
    for name in ALL_OUTPUTS + ("visible",):
        if getattr(out, name) is not None:
            setattr(out, name, getattr(out, name).cpu())
    return out


def render_surfels_ref(scene, background=None, **kw):
    return render_surfels_reference(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                    scene["colors"], scene["viewmat"], scene["K"], scene["width"], scene["height"],
                                    sh_degree=scene["sh_degree"], features=scene["features"], background=background,
                                    **kw)
