"""Geometric consistency of depth maps between views (the forward-backward check of MVS fusion, as in COLMAP's
and MVSNet's): a pixel's depth is trusted when another view's own depth map, read where the pixel lands, sends it
back to within `max_px` pixels and `max_rel` relative depth.

Per-view photo-consistency cannot tell a right depth from a wrong one where the cost curve is flat or fooled:
textureless walls, repeated leaves, and pixels a source view cannot see (its image there shows the occluder).
Two views rarely agree on the same wrong surface, so agreement is strong evidence; a pixel occluded in every
other view has no such evidence and is left out.
"""
from __future__ import annotations

from typing import Sequence

import torch

from warpgs.data.camera import Camera


def _pixel_grid(cam: Camera, device) -> tuple[torch.Tensor, torch.Tensor]:
    v, u = torch.meshgrid(torch.arange(cam.height, device=device, dtype=torch.float64) + 0.5,
                          torch.arange(cam.width, device=device, dtype=torch.float64) + 0.5, indexing="ij")
    return u.reshape(-1), v.reshape(-1)


def _lift(cam: Camera, u: torch.Tensor, v: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """Pixels (corner-origin) at camera depth -> world points [N, 3]."""
    dev = depth.device
    xc = torch.stack([(u - cam.cx) / cam.fx * depth, (v - cam.cy) / cam.fy * depth, depth], -1)
    view = torch.as_tensor(cam.viewmat, device=dev)
    return (xc - view[:3, 3]) @ view[:3, :3]


def _project(cam: Camera, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World points -> (u, v, z); points behind the camera get z <= 0 (and meaningless u, v)."""
    view = torch.as_tensor(cam.viewmat, device=xyz.device)
    xc = xyz @ view[:3, :3].T + view[:3, 3]
    z = xc[:, 2]
    safe = torch.where(z > 1e-9, z, torch.ones_like(z))
    return xc[:, 0] / safe * cam.fx + cam.cx, xc[:, 1] / safe * cam.fy + cam.cy, z


def consistent_views(ref_cam: Camera, ref_depth: torch.Tensor, others: Sequence[tuple[Camera, torch.Tensor,
                     torch.Tensor]], max_px: float = 1.0, max_rel: float = 0.03) -> tuple[torch.Tensor, torch.Tensor]:
    """(agree, checked): [H, W] counts of the other views whose depth agrees with `ref_depth` at each pixel, and of
    those that could be asked (the point lands inside them, in front, on a pixel with a valid depth).

    ref_depth: [H, W] camera depth (float64 preferred); others: (camera, depth [h, w], valid [h, w] bool) per view.
    Another view is read at the pixel the point falls in (nearest: interpolating across a depth edge would invent
    a surface that is in neither map)."""
    h, w = ref_depth.shape
    if (h, w) != (ref_cam.height, ref_cam.width):
        raise ValueError(f"ref_depth: {w}x{h} does not match camera {ref_cam.name!r} "
                         f"({ref_cam.width}x{ref_cam.height})")
    dev = ref_depth.device
    d = ref_depth.reshape(-1).double()
    u, v = _pixel_grid(ref_cam, dev)
    world = _lift(ref_cam, u, v, d)
    agree = torch.zeros(h * w, dtype=torch.int32, device=dev)
    checked = torch.zeros_like(agree)
    for cam, depth, valid in others:
        if depth.shape != (cam.height, cam.width) or valid.shape != depth.shape:
            raise ValueError(f"depth map of {cam.name!r}: shape {tuple(depth.shape)} (valid {tuple(valid.shape)}) "
                             f"does not match its camera ({cam.width}x{cam.height})")
        qu, qv, z = _project(cam, world)
        col, row = torch.floor(qu).long(), torch.floor(qv).long()
        ok = (z > 0) & (d > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        col, row = col.clamp(0, cam.width - 1), row.clamp(0, cam.height - 1)
        d_other = depth.double()[row, col]
        ok &= valid[row, col] & (d_other > 0)
        back = _lift(cam, col.double() + 0.5, row.double() + 0.5, d_other)
        bu, bv, bz = _project(ref_cam, back)
        err_px = torch.hypot(bu - u, bv - v)
        err_rel = (bz - d).abs() / d.clamp_min(1e-12)
        checked += ok.int()
        agree += (ok & (err_px < max_px) & (err_rel < max_rel)).int()
    return agree.reshape(h, w), checked.reshape(h, w)
