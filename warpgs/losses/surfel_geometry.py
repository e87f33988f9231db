"""The 2DGS geometry regularisers for surfels (Huang et al. 2024), registered on import:

    imports: [warpgs.losses.surfel_geometry]
    losses: {normal_consistency: {weight: 0.05, schedule: [linear, 0, 1, 7000, 7001]}, distortion: 0}

`normal_consistency`: mean over pixels of 1 - n_rendered . N_depth, where n_rendered is the blended surfel
normal (Σ w n, world space, facing the camera) and N_depth the normal of the surface the rendered depth map
describes (cross product of its finite differences), scaled by the (detached) alpha as 2DGS does.
`distortion`: the mean of the rasterizer's per-pixel depth-distortion term (2DGS eq. 13).
Both need `model.kind: surfels` (the outputs normal / distortion exist only there).
"""
from __future__ import annotations

import torch

from warpgs.losses.registry import batch_field, register_loss, render_output


def depth_to_normal(depth: torch.Tensor, K: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """[H,W,1] camera-z depth -> [H,W,3] world-space unit normals facing the camera (0 on the 1-pixel border
    and where the finite differences degenerate)."""
    H, W = depth.shape[:2]
    K = K.to(depth)
    u = torch.arange(W, device=depth.device, dtype=depth.dtype) + 0.5
    v = torch.arange(H, device=depth.device, dtype=depth.dtype) + 0.5
    x = (u[None, :] - K[0, 2]) / K[0, 0]
    y = (v[:, None] - K[1, 2]) / K[1, 1]
    z = depth[..., 0]
    pts = torch.stack([x * z, y * z.expand(H, W), z.expand(H, W)], -1)  # camera frame
    dx = pts[1:-1, 2:] - pts[1:-1, :-2]
    dy = pts[2:, 1:-1] - pts[:-2, 1:-1]
    n = -torch.linalg.cross(dx, dy, dim=-1)  # x right, y down: cross(dx, dy) points away; flip to face the camera
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    n = n @ viewmat[:3, :3].to(depth)  # camera -> world: R^T n, written row-wise
    out = torch.zeros(H, W, 3, device=depth.device, dtype=depth.dtype)
    out[1:-1, 1:-1] = n
    return out


@register_loss("normal_consistency", outputs=("normal", "depth", "alpha"), weight=0.05)
def normal_consistency(render_out, batch, model, step) -> torch.Tensor:
    normal = render_output(render_out, "normal")
    depth = render_output(render_out, "depth")
    alpha = render_output(render_out, "alpha").detach()
    surface = depth_to_normal(depth, batch_field(batch, "K"), batch_field(batch, "viewmat")) * alpha
    return (1.0 - (normal * surface).sum(-1)).mean()


@register_loss("distortion", outputs=("distortion",), weight=0.0)
def distortion(render_out, batch, model, step) -> torch.Tensor:
    return render_output(render_out, "distortion").mean()
