"""Built-in depth estimator: plane-sweep stereo against neighbouring views (light-field sub-apertures, nearby
frames, or the other training views of a few-view capture). Needs no network weights; vectorised in torch.

For each reference view: sweep fronto-parallel planes uniformly in inverse depth; warp every source image onto
the reference through each plane's homography; score photo-consistency with a truncated colour + gradient
difference; keep, per pixel and plane, the mean of the best `best_fraction` of the sources that see it (all by
default: on fern's 3 views the mean of both sources ranked errors better than the better one alone, and the
consistency check below removes what an occluded source gets wrong; 0.5 was the old default); average that
over a small window; take the best plane with a parabolic sub-plane refinement.

Which pixels to trust (issue 15: on real 3-view captures the old rule trusted textureless walls most):
- confidence "margin" (default): how far the best cost sits below the best cost of any clearly different depth
  (more than 2 planes away). Flat cost curves (textureless) and double minima (repeated texture) score ~0.
  Reported as 1 - exp(-margin / margin_scale). The old "distinct" rule, (median - best) / median, divides by a
  median that is itself ~0 on textureless pixels and so ranked them highest.
- geometric consistency (default on; warpgs.data.depth.consistency): the depth must agree with at least `min_agree`
  other views' own depth maps; confidence is scaled by the share of the views that could check it and agree.
A pixel is valid when some source sees it, the best plane is not at either end of the sweep, and it passes the
rules above.
"""
from __future__ import annotations

import sys
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from warpgs.data.camera import Camera
from warpgs.data.depth.estimators import DepthEstimate, DepthEstimator


_CHUNK_ELEMENTS = 1 << 22  # source x plane x pixel elements per chunk of the sweep
# The estimator as it was before issue 15 (benchmarks/prior_accuracy.py scores it as "legacy").
LEGACY_SETTINGS = dict(num_sources=8, window=5, truncation=0.15, best_fraction=0.5, min_distinctiveness=0.25,
                       confidence="distinct", consistency=False)
CONFIDENCE_RULES = ("margin", "distinct")
_MARGIN_PLANES = 2  # a "clearly different" depth is more than this many planes from the best


def _features(img: torch.Tensor) -> torch.Tensor:
    """[B, 3, H, W] -> [B, 5, H, W]: colour plus the x/y gradients of the grey image (lighting-robust detail)."""
    grey = img.mean(1, keepdim=True)
    gx = F.pad(grey[..., :, 2:] - grey[..., :, :-2], (1, 1, 0, 0), mode="replicate") * 0.5
    gy = F.pad(grey[..., 2:, :] - grey[..., :-2, :], (0, 0, 1, 1), mode="replicate") * 0.5
    return torch.cat([img, 4.0 * gx, 4.0 * gy], 1)


def _box(x: torch.Tensor, window: int) -> torch.Tensor:
    """Separable mean over a window x window neighbourhood ([N, 1, H, W]); edges average what exists."""
    r = window // 2
    x = F.avg_pool2d(x, (window, 1), stride=1, padding=(r, 0), count_include_pad=False)
    return F.avg_pool2d(x, (1, window), stride=1, padding=(0, r), count_include_pad=False)


def _no_estimate(camera: Camera) -> DepthEstimate:
    """A view the sweep could not bound: every pixel invalid (its prior then constrains nothing)."""
    shape = (camera.height, camera.width)
    return DepthEstimate(inv_depth=np.zeros(shape, np.float32), valid=np.zeros(shape, bool), metric=True,
                         confidence=np.zeros(shape, np.float32))


class PlaneSweepStereo(DepthEstimator):
    """num_planes: planes per sweep (None: enough for half-pixel steps in the widest-baseline source, 16..128);
    num_sources: nearest views used per reference; window: aggregation window (pixels); truncation: cap on a
    pixel's colour+gradient difference; best_fraction: share of the seeing sources averaged per pixel;
    near/far: depth range (None: from the SfM points the view sees); confidence: "margin" or "distinct" (see the
    module doc) with its threshold min_margin / min_distinctiveness and margin_scale; consistency: keep only
    depths that min_agree other views' depth maps confirm within consistency_px pixels and consistency_rel
    relative depth; device: torch device (None: CUDA when available, else CPU); num_threads: torch CPU threads
    during a sweep (1 by default: its ops are small, and on a shared 2-core machine a second thread mostly waits,
    which measured up to 5x slower here; None keeps torch's setting)."""

    name = "plane_sweep"

    def __init__(self, num_planes: Optional[int] = None, num_sources: int = 8, window: int = 5, truncation: float = 0.15,
                 best_fraction: float = 1.0, near: Optional[float] = None, far: Optional[float] = None,
                 min_distinctiveness: float = 0.25, confidence: str = "margin", min_margin: float = 0.0,
                 margin_scale: float = 0.01, consistency: bool = True, consistency_px: float = 1.0,
                 consistency_rel: float = 0.03, min_agree: int = 1, device: Optional[str] = None,
                 num_threads: Optional[int] = 1):
        if confidence not in CONFIDENCE_RULES:
            raise ValueError(f"confidence: expected one of {CONFIDENCE_RULES}, got {confidence!r}")
        if not 0 < best_fraction <= 1:
            raise ValueError(f"best_fraction: expected a share in (0, 1], got {best_fraction}")
        if margin_scale <= 0 or consistency_px <= 0 or consistency_rel <= 0 or min_agree < 1:
            raise ValueError("margin_scale, consistency_px and consistency_rel must be > 0 and min_agree >= 1, got "
                             f"{margin_scale}, {consistency_px}, {consistency_rel}, {min_agree}")
        self.num_planes = num_planes  # None: enough for half-pixel steps in the widest-baseline source
        self.num_sources = num_sources
        self.window = window
        self.truncation = truncation
        self.best_fraction = best_fraction
        self.near, self.far = near, far
        self.min_distinctiveness = min_distinctiveness
        self.confidence = confidence
        self.min_margin, self.margin_scale = min_margin, margin_scale
        self.consistency = consistency
        self.consistency_px, self.consistency_rel, self.min_agree = consistency_px, consistency_rel, min_agree
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        self.num_threads = num_threads

    # --- depth range ---------------------------------------------------------------------------------------
    def has_depth_range(self, scene, view: int) -> bool:
        """Whether depth_range can bound the view (near/far given, or at least 3 SfM points seen)."""
        return (self.near is not None and self.far is not None) or (
            scene.points is not None and len(scene.visible_points(view)) >= 3)

    def depth_range(self, scene, view: int) -> tuple[float, float]:
        """near/far given at construction, else from the depths of the SfM points the view sees."""
        if self.near is not None and self.far is not None:
            return self.near, self.far
        if not self.has_depth_range(scene, view):
            raise ValueError(f"plane sweep for view {scene.names[view]!r}: no SfM points to bound the depth range; "
                             "pass near= and far=")
        z = scene.cameras[view].world_to_camera(scene.points.xyz[scene.visible_points(view)])[:, 2]
        z = z[z > 0]
        near, far = np.percentile(z, 1) * 0.8, np.percentile(z, 99) * 1.25
        return (self.near or float(near)), (self.far or float(far))

    # --- the sweep -----------------------------------------------------------------------------------------
    def sweep(self, ref_img: np.ndarray, ref_cam: Camera, src_imgs: Sequence[np.ndarray],
              src_cams: Sequence[Camera], near: float, far: float) -> DepthEstimate:
        """Inverse depth of the reference view from source images (all [H, W, 3] float in [0, 1])."""
        dev = self.device
        h, w = ref_cam.height, ref_cam.width
        n_planes = self.num_planes or self.planes_for(ref_cam, src_cams, near, far)
        inv = torch.linspace(1.0 / far, 1.0 / near, n_planes, dtype=torch.float64, device=dev)
        ref = _features(torch.as_tensor(ref_img, device=dev).permute(2, 0, 1)[None].float())[0]
        v, u = torch.meshgrid(torch.arange(h, device=dev, dtype=torch.float64) + 0.5,
                              torch.arange(w, device=dev, dtype=torch.float64) + 0.5, indexing="ij")
        pix = torch.stack([u.ravel(), v.ravel(), torch.ones_like(u.ravel())])  # [3, HW]
        K_ref_inv = torch.linalg.inv(torch.as_tensor(ref_cam.K, device=dev))
        sources = []
        for img, cam in zip(src_imgs, src_cams):
            # X_src = R X_ref + t and X_ref = z K_ref^-1 p, so p_src ~ (K_src R K_ref^-1) p + (K_src t) / z.
            rel = torch.as_tensor(cam.viewmat @ ref_cam.camtoworld, device=dev)
            K_src = torch.as_tensor(cam.K, device=dev)
            a = (K_src @ rel[:3, :3] @ K_ref_inv @ pix).float()  # [3, HW]
            b = (K_src @ rel[:3, 3]).float()
            feat = _features(torch.as_tensor(img, device=dev).permute(2, 0, 1)[None].float())
            sources.append((a, b, feat, cam))
        # Planes go in chunks so the [sources, planes, H, W] temporaries stay small (memory-bound otherwise).
        chunk = max(1, _CHUNK_ELEMENTS // (len(sources) * h * w))
        per_pixel = torch.empty(n_planes, h, w, device=dev)
        seen = torch.empty(n_planes, h, w, device=dev)
        for lo in range(0, n_planes, chunk):
            rho = inv[lo:lo + chunk].float()[:, None]
            cost = torch.stack([self._source_cost(ref, a, b, feat, cam, rho, h, w) for a, b, feat, cam in sources])
            per_pixel[lo:lo + chunk], seen[lo:lo + chunk] = self._best_sources(cost)
        num, den = _box(per_pixel[:, None], self.window)[:, 0], _box(seen[:, None], self.window)[:, 0]
        volume = torch.where(den > 0.5, num / den.clamp(min=1e-6), torch.full_like(num, float("inf")))
        return self._select(volume, inv)

    def _source_cost(self, ref: torch.Tensor, a: torch.Tensor, b: torch.Tensor, feat: torch.Tensor, cam: Camera,
                     rho: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """[d, H, W] truncated feature difference between the reference and one source warped through planes of
        inverse depth rho [d, 1]; NaN where the plane point falls outside the source image or behind it."""
        z = a[2] + b[2] * rho  # [d, HW]
        front = z > 1e-6
        z = torch.where(front, z, torch.ones_like(z))
        # Normalised grid coordinates directly (grid_sample, align_corners=False: -1/+1 at the outer edges);
        # points behind the source camera are sent off-image.
        gx = torch.where(front, (a[0] + b[0] * rho) / z * (2.0 / cam.width) - 1, torch.full_like(z, 2.0))
        gy = (a[1] + b[1] * rho) / z * (2.0 / cam.height) - 1
        d = rho.shape[0]
        warped = F.grid_sample(feat, torch.stack([gx, gy], -1).reshape(1, d * h, w, 2), mode="bilinear",
                               padding_mode="zeros", align_corners=False).reshape(feat.shape[1], d, h, w)
        diff = (warped - ref[:, None]).abs().mean(0).clamp_(max=self.truncation)
        inside = ((gx.abs() <= 1) & (gy.abs() <= 1)).reshape(d, h, w)
        return torch.where(inside, diff, torch.full_like(diff, float("nan")))

    def _best_sources(self, cost: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per pixel and plane, the mean of the best `best_fraction` of the sources that see it (at least one),
        so a source occluded there does not vote; and whether any source sees it. cost: [S, d, H, W]."""
        ordered = torch.nan_to_num(cost, nan=float("inf")).sort(0).values  # unseen last
        n_seen = torch.isfinite(ordered).sum(0, keepdim=True)
        k = (n_seen.float() * self.best_fraction).round().clamp(min=1).long()
        summed = torch.nan_to_num(ordered, posinf=0.0).cumsum(0).gather(0, k - 1)[0]
        seen = (n_seen[0] > 0).float()
        return summed / k[0] * seen, seen

    @staticmethod
    def planes_for(ref_cam: Camera, src_cams: Sequence[Camera], near: float, far: float, step_px: float = 0.5,
                   bounds: tuple[int, int] = (16, 128)) -> int:
        """Planes needed so that neighbouring planes shift the widest-baseline source by <= step_px pixels."""
        baseline = max(float(np.linalg.norm(c.center - ref_cam.center)) for c in src_cams)
        focal = max(max(c.fx, c.fy) for c in src_cams)
        span = focal * baseline * (1.0 / near - 1.0 / far)  # disparity range in pixels
        return int(np.clip(np.ceil(span / step_px) + 1, *bounds))

    def _select(self, volume: torch.Tensor, inv: torch.Tensor) -> DepthEstimate:
        d_count = volume.shape[0]
        finite = torch.isfinite(volume)
        vol = torch.where(finite, volume, torch.full_like(volume, self.truncation))
        c_min, idx = vol.min(0)
        # Sub-plane refinement: vertex of the parabola through the best plane and its neighbours.
        lo, hi = (idx - 1).clamp(min=0), (idx + 1).clamp(max=d_count - 1)
        c_lo, c_hi = vol.gather(0, lo[None])[0], vol.gather(0, hi[None])[0]
        curv = c_lo - 2 * c_min + c_hi
        offset = torch.where(curv > 1e-9, 0.5 * (c_lo - c_hi) / curv.clamp(min=1e-9), torch.zeros_like(curv))
        offset = offset.clamp(-0.5, 0.5).double()
        step = (inv[-1] - inv[0]) / max(d_count - 1, 1)
        inv_depth = inv[idx] + offset * step
        seen = finite.float().mean(0) > 0.5
        interior = (idx > 0) & (idx < d_count - 1)
        if self.confidence == "distinct":
            # How far the best cost sits below the median over planes (the rule before issue 15).
            median = vol.median(0).values
            score = (median - c_min) / median.clamp(min=1e-6)
            valid = seen & interior & (score > self.min_distinctiveness)
            conf = score.clamp(0, 1)
        else:
            planes = torch.arange(d_count, device=vol.device)[:, None, None]
            elsewhere = (planes - idx[None]).abs() > _MARGIN_PLANES
            second = torch.where(elsewhere, vol, torch.full_like(vol, float("inf"))).min(0).values
            margin = torch.where(torch.isfinite(second), second - c_min, torch.zeros_like(c_min)).clamp_min(0)
            valid = seen & interior & (margin > self.min_margin)
            conf = 1 - torch.exp(-margin / self.margin_scale)
        return DepthEstimate(inv_depth=inv_depth.float().cpu().numpy(), valid=valid.cpu().numpy(), metric=True,
                             confidence=torch.where(valid, conf, torch.zeros_like(conf)).float().cpu().numpy())

    # --- the estimator interface ---------------------------------------------------------------------------
    def neighbours(self, scene, view: int, sources: Sequence[int]) -> list[int]:
        centre = scene.cameras[view].center
        others = [s for s in sources if s != view]
        others.sort(key=lambda s: float(np.linalg.norm(scene.cameras[s].center - centre)))
        return others[: self.num_sources]

    def estimate(self, scene, views: Sequence[int], sources: Optional[Sequence[int]] = None) -> dict[int, DepthEstimate]:
        sources = list(scene.train if sources is None else sources)
        views = list(views)
        previous = torch.get_num_threads()
        if self.device.type == "cpu" and self.num_threads:
            torch.set_num_threads(self.num_threads)
        try:
            nbrs = {v: self.neighbours(scene, v, sources) for v in views}
            raw = {}
            # The consistency check needs the neighbours' own depth maps too (from their own neighbours).
            needed = list(dict.fromkeys(views + [n for v in views for n in nbrs[v]
                                                 if self.consistency and n not in views]))
            unbounded = [v for v in needed if not self.has_depth_range(scene, v)]
            if unbounded and all(v in unbounded for v in views):
                self.depth_range(scene, views[0])  # raises, naming the view
            for v in unbounded:  # e.g. 3 views around a 360° capture: a view may share no triangulated point
                print(f"depth priors: view {scene.names[v]!r} sees fewer than 3 SfM points, which bound the plane "
                      "sweep's depth range: it gets no prior (give data.depth_prior_options near= and far= to "
                      "sweep it)", file=sys.stderr)
            for v in needed:
                near_views = nbrs.get(v) or self.neighbours(scene, v, sources)
                if not near_views:
                    raise ValueError(f"plane sweep for view {scene.names[v]!r}: no other view to match against")
                if v in unbounded:
                    raw[v] = _no_estimate(scene.cameras[v])
                    continue
                near, far = self.depth_range(scene, v)
                raw[v] = self.sweep(scene.image_np(v)[0], scene.cameras[v],
                                    [scene.image_np(s)[0] for s in near_views], [scene.cameras[s] for s in near_views],
                                    near, far)
            if not self.consistency:
                return {v: raw[v] for v in views}
            return {v: self._checked(scene, v, raw, nbrs[v]) for v in views}
        finally:
            torch.set_num_threads(previous)

    def _checked(self, scene, view: int, raw: dict, neighbours: Sequence[int]) -> DepthEstimate:
        """raw[view] with its validity and confidence narrowed by the neighbours' depth maps."""
        from warpgs.data.depth.consistency import consistent_views

        def depth_of(est):
            inv = torch.as_tensor(est.inv_depth, device=self.device, dtype=torch.float64)
            return torch.where(inv > 0, 1.0 / inv.clamp_min(1e-12), torch.zeros_like(inv))

        others = [(scene.cameras[n], depth_of(raw[n]), torch.as_tensor(raw[n].valid, device=self.device))
                  for n in neighbours]
        agree, checked = consistent_views(scene.cameras[view], depth_of(raw[view]), others, self.consistency_px,
                                          self.consistency_rel)
        est = raw[view]
        valid = est.valid & (agree >= self.min_agree).cpu().numpy()
        share = (agree.float() / checked.clamp_min(1).float()).cpu().numpy()
        conf = np.where(valid, (est.confidence if est.confidence is not None else 1.0) * share, 0.0)
        return DepthEstimate(inv_depth=est.inv_depth, valid=valid, metric=est.metric,
                             confidence=conf.astype(np.float32))
