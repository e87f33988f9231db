"""Where a primitive lands on screen, in torch, for the densification strategy: the pixel-space gradient of a
primitive's projected mean recovered from its 3D gradient (when the renderer exposes no 2D means), and its 3-sigma
screen radius (for the screen-size rule). Both mirror kernels/project.py's projection."""
from __future__ import annotations

import torch

from warpgs.model.gaussians import GaussianModel, quat_to_rotmat
from warpgs.render.defaults import DEFAULT_LOW_PASS

LOW_PASS = DEFAULT_LOW_PASS  # px^2, what training renders add (kernels/project.py)


def _camera_frame(means: torch.Tensor, viewmat: torch.Tensor):
    R, t = viewmat[:3, :3].to(means), viewmat[:3, 3].to(means)
    return R, means @ R.T + t


def screen_grads_from_means_grad(means: torch.Tensor, means_grad: torch.Tensor, viewmat: torch.Tensor,
                                 K: torch.Tensor, near: float = 0.01) -> torch.Tensor:
    """[N,2] pixel-space gradient g2d with J^T g2d = the camera-frame 3D gradient, least squares (see module doc).
    Primitives behind the near plane get 0."""
    R, p = _camera_frame(means.detach(), viewmat)
    g = means_grad.detach() @ R.T  # dL/dp = R dL/dmu
    z = p[:, 2].clamp_min(near)
    fx, fy = K[0, 0].to(means), K[1, 1].to(means)
    u, v = p[:, 0] / z, p[:, 1] / z
    # J = [[a, 0, -a u], [0, b, -b v]] with a = fx/z, b = fy/z; solve (J J^T) g2 = J g in closed form.
    a, b = fx / z, fy / z
    jg = torch.stack([a * (g[:, 0] - u * g[:, 2]), b * (g[:, 1] - v * g[:, 2])], 1)
    m00, m11, m01 = a * a * (1 + u * u), b * b * (1 + v * v), a * b * u * v
    det = (m00 * m11 - m01 * m01).clamp_min(1e-30)  # = a^2 b^2 (1 + u^2 + v^2) > 0
    g2 = torch.stack([(m11 * jg[:, 0] - m01 * jg[:, 1]) / det, (m00 * jg[:, 1] - m01 * jg[:, 0]) / det], 1)
    return torch.where((p[:, 2] >= near)[:, None], g2, torch.zeros_like(g2))


def screen_radii(model: GaussianModel, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                 near: float = 0.01) -> torch.Tensor:
    """[N] 3-sigma screen radius in pixels (0 behind the near plane), mirroring the projection kernel."""
    with torch.no_grad():
        means = model.means
        R, p = _camera_frame(means, viewmat)
        z = p[:, 2].clamp_min(near)
        fx, fy, cx, cy = (K[0, 0].item(), K[1, 1].item(), K[0, 2].item(), K[1, 2].item())
        tx, ty = 0.5 * width / fx, 0.5 * height / fy
        u = (p[:, 0] / z).clamp(-(cx / fx + 0.3 * tx), (width - cx) / fx + 0.3 * tx)
        v = (p[:, 1] / z).clamp(-(cy / fy + 0.3 * ty), (height - cy) / fy + 0.3 * ty)
        zero = torch.zeros_like(z)
        J = torch.stack([torch.stack([fx / z, zero, -fx * u / z], -1),
                         torch.stack([zero, fy / z, -fy * v / z], -1)], -2)
        scales = model.scales
        if scales.shape[1] < 3:
            scales = torch.cat([scales, scales.new_zeros(len(scales), 3 - scales.shape[1])], 1)
        T = J @ R @ (quat_to_rotmat(model.quats) * scales.clamp_max(1e8)[:, None, :])
        cov = T @ T.transpose(1, 2)
        a, b, c = cov[:, 0, 0] + LOW_PASS, cov[:, 0, 1], cov[:, 1, 1] + LOW_PASS
        mid = 0.5 * (a + c)
        lam = mid + ((0.5 * (a - c)) ** 2 + b * b).sqrt()
        r = 3.0 * lam.sqrt()
        return torch.where(p[:, 2] >= near, r, torch.zeros_like(r))
