"""Virtual views for few-view training (train.virtual_views; FSGS's pseudo views, our formulation).

With three training views a model can fit every training pixel and still hold floaters that only a new viewpoint
shows. Every `train.virtual_views` steps the trainer also renders a camera placed between a training camera and one
of its `NEIGHBOURS` nearest (position and rotation interpolated at a random fraction; with three views, any two;
around a 360° capture, adjacent ones, never across the object) and fits it to the depth prior's confident pixels of
all training views, lifted to 3D and projected into it: each virtual pixel takes the nearest lifted point's colour
and inverse depth. The loss is an L1 on colour and on inverse depth over the pixels that got a point
(`train.virtual_rgb`, `train.virtual_depth` weigh them).

Projected points leave gaps, and a far point seen through a gap between near ones would ask for background where
the surface is: a pixel is kept only where its inverse depth is at least `SEE_THROUGH` of the largest in its 5x5
neighbourhood. Cameras are drawn from (seed, step), so a resumed run draws the same ones.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from warpgs.losses.marr import masked_mean
from warpgs.train.few_views import FewViewsRule
from warpgs.train.lifted_prior import lifted_prior

SEE_THROUGH = 0.9  # a virtual pixel's inverse depth over the largest in its 5x5 neighbourhood, at least
NEIGHBOURHOOD = 5
MAX_POINTS = 2_000_000  # lifted prior pixels kept (all confident pixels of a few training views fit)
NEIGHBOURS = 2  # a virtual camera lies between a training camera and one of this many nearest (by centre)
# train.virtual_views=auto: on (every step) with at most this many training views. Measured (docs/sparse_view.md):
# 3 views a tie on 7 real LLFF scenes (-0.05 dB, H200) at 2.6x the training time and on a 360° capture; 4 views a tie
# (-0.02); 9 (a light field) -1.26, 24 (360°) -3.1. sparse_llff leaves them off.
AUTO_MAX_VIEWS = 3
RULE = FewViewsRule("virtual views", "train.virtual_views", AUTO_MAX_VIEWS, 1)


def virtual_every(setting, num_train_views: int) -> int:
    """The period in steps that train.virtual_views asks for with this many training views (0: off)."""
    return RULE.value(setting, num_train_views, int)


def virtual_views_note(setting, every: int, num_train_views: int) -> str:
    """The start line's words on virtual views: their period when on, why not when "auto" left them off, else ""."""
    return RULE.note(setting, every, num_train_views, f"; virtual views every {every} step(s)")


@dataclass
class VirtualView:
    """A camera between two training cameras and its targets: what Trainer.make_batch and Trainer.render take."""

    viewmat: torch.Tensor  # [4, 4] world -> camera
    K: torch.Tensor  # [3, 3]
    width: int
    height: int
    image: torch.Tensor  # [H, W, 3] the nearest lifted point's colour (0 where none)
    inv_depth: torch.Tensor  # [H, W, 1] its inverse depth (0 where none)
    mask: torch.Tensor  # [H, W, 1] bool: pixels with a target
    name: str = "virtual"
    index: int = -1


def rotation_log(R: np.ndarray) -> np.ndarray:
    """The rotation vector (axis times angle) of a rotation matrix; angles below pi."""
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.arccos(cos))
    if angle < 1e-9:
        return np.zeros(3)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2.0 * np.sin(angle))
    return w * angle


def rotation_exp(v: np.ndarray) -> np.ndarray:
    """The rotation matrix of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.eye(3)
    k = v / angle
    skew = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * skew + (1.0 - np.cos(angle)) * (skew @ skew)


def camera_centre(viewmat: np.ndarray) -> np.ndarray:
    """The camera's centre in world space, from its world-to-camera matrix."""
    return -viewmat[:3, :3].T @ viewmat[:3, 3]


def between(viewmat_a: np.ndarray, viewmat_b: np.ndarray, t: float) -> np.ndarray:
    """The world-to-camera matrix a fraction t of the way from camera a to camera b: the centre on the segment
    between theirs, the rotation on the shortest arc between theirs (t=0: a, t=1: b)."""
    rot_a, rot_b = viewmat_a[:3, :3], viewmat_b[:3, :3]
    centre_a, centre_b = camera_centre(viewmat_a), camera_centre(viewmat_b)
    rot = rot_a @ rotation_exp(t * rotation_log(rot_a.T @ rot_b))
    centre = (1.0 - t) * centre_a + t * centre_b
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = -rot @ centre
    return out


def neighbour_pairs(viewmats: Sequence[np.ndarray], neighbours: int = NEIGHBOURS) -> list[tuple[int, int]]:
    """(a, b) for every camera a and each of its `neighbours` nearest cameras b by centre distance (ties: lower
    index first)."""
    centres = np.stack([camera_centre(v) for v in viewmats])
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    k = min(neighbours, len(viewmats) - 1)
    return [(a, int(b)) for a in range(len(viewmats)) for b in np.argsort(dist[a], kind="stable")[:k]]


def splat_points(points: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int,
                 height: int, near: float = 1e-3):
    """(image [H, W, 3], inverse depth [H, W, 1], mask [H, W, 1]) of the nearest point in each pixel, pixels
    seen through a gap between nearer points dropped (SEE_THROUGH)."""
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    front = z > near
    cam, z, colors = cam[front], z[front], colors[front]
    u = torch.floor(K[0, 0] * cam[:, 0] / z + K[0, 2])
    v = torch.floor(K[1, 1] * cam[:, 1] / z + K[1, 2])
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    pixel = (v[inside] * width + u[inside]).long()
    inv, colors = 1.0 / z[inside], colors[inside]
    nearest = torch.zeros(height * width, dtype=inv.dtype, device=inv.device)
    nearest.scatter_reduce_(0, pixel, inv, "amax")
    wins = inv >= nearest[pixel]  # ties: either point's colour
    image = torch.zeros(height * width, 3, dtype=colors.dtype, device=colors.device)
    image[pixel[wins]] = colors[wins]
    inv_map = nearest.view(1, 1, height, width)
    around = F.max_pool2d(inv_map, NEIGHBOURHOOD, stride=1, padding=NEIGHBOURHOOD // 2)
    mask = (inv_map > 0) & (inv_map >= SEE_THROUGH * around)
    return image.view(height, width, 3), inv_map.view(height, width, 1), mask.view(height, width, 1)


class VirtualViews:
    """Draws virtual views between the training cameras (`cameras`: (viewmat [4,4], K [3,3], width, height) each)
    with the targets from `points` / `colors` (the lifted prior pixels, world space, on the training device)."""

    def __init__(self, cameras: Sequence[tuple], points: torch.Tensor, colors: torch.Tensor, seed: int = 0):
        if len(cameras) < 2:
            raise ValueError(f"train.virtual_views: needs at least 2 training views to place cameras between, got "
                             f"{len(cameras)}")
        self.cameras = [(np.asarray(v, np.float64), np.asarray(k, np.float64), int(w), int(h))
                        for v, k, w, h in cameras]
        self.pairs = neighbour_pairs([v for v, _, _, _ in self.cameras])
        self.points, self.colors = points, colors
        self.seed = int(seed)

    def draw(self, step: int) -> VirtualView:
        """The virtual view of `step` (the same for the same seed and step)."""
        rng = np.random.default_rng([self.seed, int(step)])
        a, b = self.pairs[int(rng.integers(len(self.pairs)))]
        t = float(rng.uniform(0.0, 1.0))
        view_a, K, width, height = self.cameras[a]
        viewmat = between(view_a, self.cameras[b][0], t)
        device = self.points.device
        vm = torch.as_tensor(viewmat, dtype=torch.float32, device=device)
        Kt = torch.as_tensor(K, dtype=torch.float32, device=device)
        with torch.no_grad():
            image, inv, mask = splat_points(self.points, self.colors, vm, Kt, width, height)
        return VirtualView(viewmat=vm, K=Kt, width=width, height=height, image=image, inv_depth=inv, mask=mask)


def virtual_loss(out, view: VirtualView, rgb_weight: float, depth_weight: float) -> torch.Tensor:
    """rgb_weight * mean |rendered colour - target| + depth_weight * mean |rendered inverse depth - target| over
    the view's pixels with a target (0, still connected to the graph, when it has none)."""
    return (rgb_weight * masked_mean((out.rgb - view.image).abs(), view.mask)
            + depth_weight * masked_mean((out.inv_depth - view.inv_depth).abs(), view.mask))


def virtual_views_for(scene, train_views: Sequence[int], min_confidence: float, device,
                      seed: int) -> VirtualViews:
    """The sampler over these training views, with every prior pixel of confidence >= min_confidence lifted (at
    most MAX_POINTS). A scene without depth priors is an error naming the key."""
    views = list(train_views)
    pixels = sum(scene.cameras[v].width * scene.cameras[v].height for v in views)
    cloud = lifted_prior(scene, views, min(pixels, MAX_POINTS), min_confidence, seed + 2, "train.virtual_views",
                         "train.virtual_views")
    xyz, rgb = cloud.tensors()
    cameras = [(scene.cameras[v].viewmat, scene.cameras[v].K, scene.cameras[v].width, scene.cameras[v].height)
               for v in views]
    return VirtualViews(cameras, xyz.float().to(device), rgb.float().to(device), seed=seed)
