"""The oracle: a float64, brute-force, pure-torch 3D Gaussian renderer written for obviousness, not speed.

Every Gaussian is evaluated at every pixel; no tiles, no culling beyond the near/far planes. It follows the
same rules as the Warp renderer (3DGS blending, EWA projection with the low-pass (0.3 px² by default) and the 1.3x
field-of-view clamp of the Jacobian, SH + 0.5 clamped at 0), so values and autograd gradients can be
compared directly.
"""
import math

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]
SH_C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435]


def quat_to_rotation(q):
    q = q / torch.sqrt(torch.clamp((q * q).sum(-1, keepdim=True), min=1e-24))
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)


def sh_to_rgb(sh, degree, d):
    """sh [N,K,3], d [N,3] unit directions."""
    x, y, z = (d[:, i : i + 1] for i in range(3))
    out = SH_C0 * sh[:, 0]
    if degree > 0:
        out = out - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        out = (out + SH_C2[0] * x * y * sh[:, 4] + SH_C2[1] * y * z * sh[:, 5]
               + SH_C2[2] * (2 * zz - xx - yy) * sh[:, 6] + SH_C2[3] * x * z * sh[:, 7]
               + SH_C2[4] * (xx - yy) * sh[:, 8])
    if degree > 2:
        out = (out + SH_C3[0] * y * (3 * xx - yy) * sh[:, 9] + SH_C3[1] * x * y * z * sh[:, 10]
               + SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11] + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
               + SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + SH_C3[5] * z * (xx - yy) * sh[:, 14]
               + SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15])
    return torch.clamp(out + 0.5, min=0.0)


def render_reference(means, quats, scales, opacities, colors, viewmat, K, width, height, *, sh_degree=None,
                     features=None, background=None, near=0.01, far=1e10, pixels=None, alpha_min=1.0 / 255.0,
                     transmittance_min=1e-4, alpha_max=0.99, low_pass=0.3):
    """Returns a dict of [H,W,C] float64 images: rgb, alpha, depth, inv_depth and (if given) features.

    pixels: optional [P,2] integer (x, y) pixel indices; then only those are rendered and values are [P,C]
    (for checking large scenes, where all pixels x all Gaussians would not fit in memory).
    """
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    p = means @ R.T + t
    z = p[:, 2]
    valid = (z >= near) & (z <= far)
    zs = torch.clamp(z, min=near)

    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    xz = torch.clamp(p[:, 0] / zs, min=-(cx / fx + 0.3 * tan_x), max=(width - cx) / fx + 0.3 * tan_x)
    yz = torch.clamp(p[:, 1] / zs, min=-(cy / fy + 0.3 * tan_y), max=(height - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(zs)
    J = torch.stack([torch.stack([fx / zs, zero, -fx * xz / zs], -1),
                     torch.stack([zero, fy / zs, -fy * yz / zs], -1)], -2)  # [N,2,3]
    M = quat_to_rotation(quats) * torch.clamp(scales, -1e8, 1e8)[:, None, :]  # R_q diag(s)
    T = J @ R @ M
    cov = T @ T.transpose(1, 2) + low_pass * torch.eye(2, dtype=means.dtype, device=means.device)
    conic = torch.linalg.inv(cov)
    mean2d = torch.stack([fx * p[:, 0] / zs + cx, fy * p[:, 1] / zs + cy], -1)
    if mean2d.requires_grad:
        mean2d.retain_grad()  # tests read dL/dmeans2d from out["means2d"].grad

    if sh_degree is None:
        rgb = colors
    else:
        campos = -R.T @ t
        d = means - campos
        d = d / torch.sqrt(torch.clamp((d * d).sum(-1, keepdim=True), min=1e-24))
        rgb = sh_to_rgb(colors, sh_degree, d)

    if pixels is None:
        ys, xs = torch.meshgrid(torch.arange(height, dtype=means.dtype, device=means.device),
                                torch.arange(width, dtype=means.dtype, device=means.device), indexing="ij")
        pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1) + 0.5  # [P,2] pixel centres
    else:
        pix = pixels.to(means.dtype) + 0.5
    delta = pix[:, None, :] - mean2d[None, :, :]  # [P,N,2]
    q = torch.einsum("pni,nij,pnj->pn", delta, conic, delta)
    alpha = torch.clamp(opacities[None, :] * torch.exp(-0.5 * q), max=alpha_max)
    keep = valid[None, :] & (alpha >= alpha_min)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))

    order = torch.argsort(torch.where(valid, z, torch.full_like(z, math.inf)).detach(), stable=True)
    alpha = alpha[:, order]
    # A Gaussian is blended only while the transmittance after it stays >= transmittance_min (then blending stops).
    T_after = torch.cumprod(1.0 - alpha, dim=1)
    alpha = torch.where(T_after.detach() >= transmittance_min, alpha, torch.zeros_like(alpha))
    T_after = torch.cumprod(1.0 - alpha, dim=1)
    T_before = torch.cat([torch.ones_like(T_after[:, :1]), T_after[:, :-1]], 1)
    w = alpha * T_before  # [P,N]
    T_final = T_after[:, -1] if alpha.shape[1] else torch.ones(pix.shape[0], dtype=means.dtype, device=means.device)

    zo = zs[order]
    out = {"alpha": (1.0 - T_final)[:, None], "means2d": mean2d}
    out["rgb"] = w @ rgb[order] + (T_final[:, None] * background[None, :] if background is not None else 0.0)
    out["depth"] = (w @ zo)[:, None] / torch.clamp(out["alpha"], min=1e-10)
    out["inv_depth"] = (w @ (1.0 / zo))[:, None]
    if features is not None:
        out["features"] = w @ features[order]
    if pixels is not None:
        return out
    return {k: v if k == "means2d" else v.reshape(height, width, -1) for k, v in out.items()}
