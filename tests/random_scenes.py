"""Random test scenes for the 3D rasterizer: overlapping, semi-transparent, off-screen and behind-camera
Gaussians seen by a rotated, translated camera. Small enough for the brute-force reference."""
import math

import torch


def look_at(eye, target, down=(0.0, 1.0, 0.0)):
    """World-to-camera 4x4 (OpenCV: x right, y down, z forward) for a camera at `eye` looking at `target`."""
    eye, target, down = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, down))
    z = (target - eye) / (target - eye).norm()
    x = torch.linalg.cross(down, z)  # x = y × z
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])  # rows: camera axes in world coordinates
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = R
    view[:3, 3] = -R @ eye
    return view


def intrinsics(width, height, fov_x_deg=60.0):
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)


def random_scene(n=48, width=40, height=30, seed=0, sh_degree=None, num_features=0):
    """Returns a dict of float64 tensors (means, quats, scales, opacities, colors, viewmat, K, features) and sizes."""
    g = torch.Generator().manual_seed(seed)
    viewmat = look_at((0.3, -0.2, -4.0), (0.0, 0.0, 0.0))
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([1.2, 0.9, 1.0], dtype=torch.float64)
    # A few placed on purpose: behind the camera, far off-screen, and a stack on one line of sight.
    if n >= 8:
        means[0] = torch.tensor([0.3, -0.2, -6.0])  # behind
        means[1] = torch.tensor([8.0, 0.0, 0.0])  # off-screen right
        means[2] = torch.tensor([2.2, 0.0, 0.0])  # centre off-screen, footprint partly on-screen
        means[3:6] = torch.tensor([[0.0, 0.0, -0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.5]])  # overlapping stack
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.35 + 0.03
    opacities = torch.rand(n, generator=g, dtype=torch.float64) * 0.95 + 0.02
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    else:
        colors = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.4
    features = torch.randn(n, num_features, generator=g, dtype=torch.float64) if num_features else None
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmat=viewmat,
                K=intrinsics(width, height), features=features, width=width, height=height, sh_degree=sh_degree)
