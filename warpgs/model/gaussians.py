"""Learnable primitive sets: 3D Gaussians (`GaussianModel`) and 2D surfels (`SurfelModel`), their
initialisation and PLY I/O in the layouts viewers read (3DGS for Gaussians, 2DGS for surfels).

Raw parameters live in `model.params` (an nn.ParameterDict, one row per primitive):
  means [N,3], log_scales [N,3] (surfels [N,2]), quats [N,4] wxyz (unnormalised), logit_opacities [N],
  sh0 [N,1,3] (the DC coefficient), shN [N,K-1,3] (K = (max_sh_degree+1)^2), and any extras [N,C].
Activated values come from properties: `scales` = exp(log_scales), `opacities` = sigmoid(logit_opacities).
The densification strategy swaps whole Parameters (rows added/removed), so keep no references to old ones.
"""
from __future__ import annotations

import math
import re
from typing import Dict, Mapping, Optional

import numpy as np
import torch
from torch import nn

# Also re-exported from here (their old home): atomic_write_bytes, SH_C0, sh0_to_rgb, quat_to_rotmat.
from warpgs.utils.atomic_file import atomic_write_bytes  # noqa: F401
from warpgs.model.ply import read_ply, write_ply
from warpgs.model.primitive_math import SH_C0, num_sh_coeffs, quat_to_rotmat, rgb_to_sh0, sh0_to_rgb  # noqa: F401

CORE_PARAMS = ("means", "log_scales", "quats", "logit_opacities", "sh0", "shN")
MAX_SH_DEGREE = 3


def knn(points: torch.Tensor, k: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """([N, k] distances, [N, k] indices) of each point's k nearest other points, nearest first (k <= N - 1),
    on the points' device.

    Exact, with a k-d tree in float64 on the host (scipy), O(N log N): a full distance matrix (the earlier search)
    made a 122k-point SfM cloud's set-up take 18 s on 16 cores and 35 s on 2, and grows with N squared.
    """
    from scipy.spatial import cKDTree  # lazy: the render path does not need scipy

    n = points.shape[0]
    k = max(0, min(int(k), n - 1))
    if k == 0:
        return points.new_zeros(n, 0), torch.zeros(n, 0, dtype=torch.int64, device=points.device)
    host = points.detach().to("cpu", torch.float64).numpy()
    dists, idx = cKDTree(host).query(host, k=k + 1, workers=-1)
    dists, idx = dists.reshape(n, k + 1), idx.reshape(n, k + 1)
    # Drop each point's own entry. Among coincident points the tree may list another first, or (more than k + 1
    # of them) not list the point at all: then the farthest entry goes, all at distance 0 anyway.
    own = idx == np.arange(n)[:, None]
    own[~own.any(1), -1] = True
    keep = ~own
    return (torch.from_numpy(dists[keep].reshape(n, k)).to(points.device, torch.float32),
            torch.from_numpy(idx[keep].reshape(n, k)).to(points.device, torch.int64))


def knn_scale(points: torch.Tensor, k: int = 3, fallback: float = 0.01) -> torch.Tensor:
    """Per point: sqrt of the mean squared distance to its k nearest other points (as 3DGS's init)."""
    n = points.shape[0]
    if n < 2:
        return points.new_full((n,), float(fallback))
    nearest, _ = knn(points, k)
    dist2 = (nearest ** 2).mean(1).clamp_min(1e-7)  # 3DGS's floor: coincident points still get a finite log-scale
    return dist2.sqrt()


def _as_float_tensor(name: str, value, shape_tail: tuple, device=None) -> torch.Tensor:
    t = torch.as_tensor(value, device=device)
    if t.dtype == torch.uint8:
        t = t.float() / 255.0
    t = t.float()
    if t.dim() != 1 + len(shape_tail) or any(w is not None and g != w for g, w in zip(t.shape[1:], shape_tail)):
        want = "[N, " + ", ".join("*" if d is None else str(d) for d in shape_tail) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {list(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} contains NaN or Inf values")
    return t


class GaussianModel(nn.Module):
    """3D Gaussians. The surfel variant (`SurfelModel`) only changes `num_scales` and the rotation init."""

    kind = "gaussians"
    num_scales = 3
    # None on a whole model. On a model-parallel shard (train/model_parallel.py): a differentiable sum over every
    # rank's value of a tensor, for losses that read the model (means, counts over all primitives; losses/gestalt.py).
    reduce_rows = None

    def __init__(self, means, log_scales, quats, logit_opacities, sh0, shN,
                 extras: Optional[Mapping[str, torch.Tensor]] = None, active_sh_degree: int = 0):
        super().__init__()
        means = _as_float_tensor("means", means, (3,))
        n = means.shape[0]
        device = means.device
        tensors = {
            "means": means,
            "log_scales": _as_float_tensor("log_scales", log_scales, (self.num_scales,), device),
            "quats": _as_float_tensor("quats", quats, (4,), device),
            "logit_opacities": _as_float_tensor("logit_opacities", logit_opacities, (), device),
            "sh0": _as_float_tensor("sh0", sh0, (1, 3), device),
            "shN": _as_float_tensor("shN", shN, (None, 3), device),
        }
        for name, t in tensors.items():
            if t.shape[0] != n:
                raise ValueError(f"{name}: expected {n} rows (as means), got {t.shape[0]}")
        k = tensors["shN"].shape[1] + 1
        degree = math.isqrt(k) - 1
        if num_sh_coeffs(degree) != k or degree > MAX_SH_DEGREE:
            raise ValueError(f"shN: {k - 1} rest coefficients is not (d+1)^2-1 for a degree d in 0..{MAX_SH_DEGREE}")
        self.max_sh_degree = degree
        # Own copies: the optimizer updates in place and must not write into the caller's tensors (SfM points).
        self.params = nn.ParameterDict({name: nn.Parameter(t.detach().clone()) for name, t in tensors.items()})
        self._active_sh_degree = 0
        self.active_sh_degree = active_sh_degree
        for name, value in (extras or {}).items():
            self.add_extra(name, value)

    # ----- construction -----
    @classmethod
    def from_points(cls, points, colors=None, *, sh_degree: int = 3, opacity: float = 0.1, knn: int = 3,
                    max_points: Optional[int] = None, generator: Optional[torch.Generator] = None,
                    device=None) -> "GaussianModel":
        """Initialise from a point cloud (e.g. SfM points) and colours in [0,1] (or uint8); None -> grey.

        Scales: 3DGS's sqrt(mean squared distance to the `knn` nearest points), isotropic. Opacity 0.1,
        DC from colour, higher SH zero. `max_points` keeps a random subset (so a primitive budget holds
        from step 0).
        """
        points = _as_float_tensor("points", points, (3,), device)
        n = points.shape[0]
        if n == 0:
            raise ValueError("points: empty point cloud; use random_init for scenes without points")
        if colors is None:
            colors = torch.full_like(points, 0.5)
        colors = _as_float_tensor("colors", colors, (3,), points.device)
        if colors.shape[0] != n:
            raise ValueError(f"colors: expected {n} rows (as points), got {colors.shape[0]}")
        if not 0 <= int(sh_degree) <= MAX_SH_DEGREE:
            raise ValueError(f"sh_degree: expected 0..{MAX_SH_DEGREE}, got {sh_degree}")
        if not 0.0 < opacity < 1.0:
            raise ValueError(f"opacity: expected a value in (0, 1), got {opacity}")
        if max_points is not None and n > int(max_points):
            if int(max_points) < 1:
                raise ValueError(f"max_points: expected a positive integer, got {max_points}")
            keep = torch.randperm(n, generator=generator)[: int(max_points)].to(points.device)
            points, colors, n = points[keep], colors[keep], int(max_points)
        scale = knn_scale(points, knn)
        log_scales = scale.log()[:, None].repeat(1, cls.num_scales)
        logit = torch.full((n,), math.log(opacity / (1.0 - opacity)), device=points.device)
        sh0 = rgb_to_sh0(colors.clamp(0.0, 1.0))[:, None, :]
        shN = torch.zeros(n, num_sh_coeffs(sh_degree) - 1, 3, device=points.device)
        return cls(points, log_scales, cls._init_quats(n, generator).to(points.device), logit, sh0, shN)

    @classmethod
    def random_init(cls, num_points: int, bbox_min, bbox_max, *, generator: Optional[torch.Generator] = None,
                    device=None, **kwargs) -> "GaussianModel":
        """Uniform points with random colours inside the box [bbox_min, bbox_max] (for scenes without points)."""
        if int(num_points) != num_points or num_points < 1:
            raise ValueError(f"num_points: expected a positive integer, got {num_points}")
        lo = torch.as_tensor(bbox_min, dtype=torch.float32).reshape(-1)
        hi = torch.as_tensor(bbox_max, dtype=torch.float32).reshape(-1)
        if lo.numel() != 3 or hi.numel() != 3 or not bool((hi > lo).all()):
            raise ValueError(f"bbox_min/bbox_max: expected 3-vectors with bbox_max > bbox_min, got {lo.tolist()}, {hi.tolist()}")
        u = torch.rand(int(num_points), 3, generator=generator)
        colors = torch.rand(int(num_points), 3, generator=generator)
        return cls.from_points((lo + u * (hi - lo)).to(device), colors.to(device), generator=generator, **kwargs)

    @staticmethod
    def _init_quats(n: int, generator: Optional[torch.Generator]) -> torch.Tensor:
        q = torch.zeros(n, 4)
        q[:, 0] = 1.0  # identity: isotropic 3D Gaussians do not care about orientation
        return q

    def add_extra(self, name: str, values) -> None:
        """Register a learnable per-primitive [N,C] parameter (e.g. a language latent). Call before building
        the optimizer; the strategy copies/removes its rows like the others and PLY files carry it."""
        if not isinstance(name, str) or not name.isidentifier() or name in CORE_PARAMS or name in self.params:
            raise ValueError(f"name: {name!r} must be a new identifier, not one of {list(self.params)}")
        if _PLY_CORE_NAME.match(name):
            raise ValueError(f"name: {name!r} clashes with a standard PLY property prefix")
        t = _as_float_tensor(name, values, (None,), self.device)
        if t.shape[0] != self.num_primitives:
            raise ValueError(f"{name}: expected {self.num_primitives} rows, got {t.shape[0]}")
        self.params[name] = nn.Parameter(t.detach().clone())

    # ----- views -----
    @property
    def num_primitives(self) -> int:
        return self.params["means"].shape[0]

    def __len__(self) -> int:
        return self.num_primitives

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    @property
    def extra_names(self) -> list:
        return [n for n in self.params if n not in CORE_PARAMS]

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    @property
    def quats(self) -> torch.Tensor:
        return self.params["quats"]

    @property
    def log_scales(self) -> torch.Tensor:
        return self.params["log_scales"]

    @property
    def scales(self) -> torch.Tensor:
        return self.params["log_scales"].exp()

    @property
    def logit_opacities(self) -> torch.Tensor:
        return self.params["logit_opacities"]

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["logit_opacities"])

    @property
    def sh0(self) -> torch.Tensor:
        return self.params["sh0"]

    @property
    def shN(self) -> torch.Tensor:
        return self.params["shN"]

    @property
    def active_sh_degree(self) -> int:
        return self._active_sh_degree

    @active_sh_degree.setter
    def active_sh_degree(self, degree: int) -> None:
        if int(degree) != degree or not 0 <= degree <= self.max_sh_degree:
            raise ValueError(f"active_sh_degree: expected 0..{self.max_sh_degree}, got {degree}")
        self._active_sh_degree = int(degree)

    def sh_coeffs(self) -> torch.Tensor:
        """[N, (active+1)^2, 3]: only the active bands, so the renderer does not evaluate unused ones."""
        k = num_sh_coeffs(self._active_sh_degree)
        return torch.cat([self.params["sh0"], self.params["shN"][:, : k - 1]], 1)

    def render_inputs(self) -> dict:
        """Keyword arguments for `rasterize` (or `rasterize_surfels`): activated values, differentiable."""
        return {"means": self.means, "quats": self.quats, "scales": self.scales, "opacities": self.opacities,
                "colors": self.sh_coeffs(), "sh_degree": self._active_sh_degree}

    # ----- checkpoints -----
    def to_dict(self) -> dict:
        """Everything needed to rebuild this model at any size (nn.Module.load_state_dict needs equal shapes)."""
        return {"kind": self.kind, "active_sh_degree": self._active_sh_degree,
                "params": {n: p.detach().cpu().clone() for n, p in self.params.items()}}

    @staticmethod
    def from_dict(state: Mapping, device=None) -> "GaussianModel":
        kind = state.get("kind")
        if kind not in MODEL_KINDS:
            raise ValueError(f"kind: expected one of {sorted(MODEL_KINDS)}, got {kind!r}")
        params = {n: torch.as_tensor(t).to(device) for n, t in state["params"].items()}
        missing = [n for n in CORE_PARAMS if n not in params]
        if missing:
            raise ValueError(f"params: missing {missing}")
        extras = {n: t for n, t in params.items() if n not in CORE_PARAMS}
        return MODEL_KINDS[kind](*(params[n] for n in CORE_PARAMS), extras=extras,
                                 active_sh_degree=int(state.get("active_sh_degree", 0)))

    # ----- PLY -----
    def save_ply(self, path, *, include_extras: bool = True) -> None:
        """Binary little-endian PLY in the 3DGS (or 2DGS for surfels) layout, written atomically.

        Extras go after the standard properties as `<name>_<j>`; viewers ignore them.
        """
        n = self.num_primitives
        cols: Dict[str, np.ndarray] = {}
        means = self.means.detach().cpu().numpy()
        for i, axis in enumerate("xyz"):
            cols[axis] = means[:, i]
        for axis in ("nx", "ny", "nz"):
            cols[axis] = np.zeros(n, np.float32)  # 3DGS writes zero normals; viewers expect the fields
        sh0 = self.sh0.detach().cpu().numpy().reshape(n, 3)
        for c in range(3):
            cols[f"f_dc_{c}"] = sh0[:, c]
        # Channel-major as 3DGS: all rest coefficients of R, then G, then B.
        rest = self.shN.detach().cpu().numpy().transpose(0, 2, 1).reshape(n, -1)
        for j in range(rest.shape[1]):
            cols[f"f_rest_{j}"] = rest[:, j]
        cols["opacity"] = self.logit_opacities.detach().cpu().numpy()
        log_scales = self.log_scales.detach().cpu().numpy()
        for j in range(self.num_scales):
            cols[f"scale_{j}"] = log_scales[:, j]
        quats = self.quats.detach().cpu().numpy()
        for j in range(4):
            cols[f"rot_{j}"] = quats[:, j]
        if include_extras:
            for name in self.extra_names:
                values = self.params[name].detach().cpu().numpy()
                for j in range(values.shape[1]):
                    cols[f"{name}_{j}"] = values[:, j]
        write_ply(path, cols)

    @staticmethod
    def load_ply(path, device=None) -> "GaussianModel":
        """Read a 3DGS/2DGS PLY: 3 scales -> GaussianModel, 2 -> SurfelModel; all SH bands active."""
        return model_from_ply_columns(read_ply(path), device=device, source=str(path))


class SurfelModel(GaussianModel):
    """2D Gaussian surfels (2DGS): two scales; the third axis of the rotation is the surfel normal."""

    kind = "surfels"
    num_scales = 2

    @staticmethod
    def _init_quats(n: int, generator: Optional[torch.Generator]) -> torch.Tensor:
        # Uniform random orientations (normalised Gaussian 4-vectors): identity would point every normal along z.
        q = torch.randn(n, 4, generator=generator)
        return q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)


MODEL_KINDS = {GaussianModel.kind: GaussianModel, SurfelModel.kind: SurfelModel}


def load_ply(path, device=None) -> GaussianModel:
    return GaussianModel.load_ply(path, device=device)


# PLY layout of the models (3DGS / 2DGS property names); the file format itself is warpgs.model.ply.
_PLY_CORE_NAME = re.compile(r"^(x|y|z|nx|ny|nz|opacity|f_dc|f_rest|scale|rot)$")


def model_from_ply_columns(cols: Mapping[str, np.ndarray], device=None, source: str = "ply") -> GaussianModel:
    def stack(names):
        missing = [nm for nm in names if nm not in cols]
        if missing:
            raise ValueError(f"{source}: missing PLY properties {missing} (not a 3DGS/2DGS Gaussian file?)")
        return torch.from_numpy(np.stack([np.asarray(cols[nm], np.float32) for nm in names], 1))

    num_scales = sum(1 for nm in cols if re.fullmatch(r"scale_\d+", nm))
    cls = {3: GaussianModel, 2: SurfelModel}.get(num_scales)
    if cls is None:
        raise ValueError(f"{source}: expected 3 (3DGS) or 2 (2DGS) scale_* properties, found {num_scales}")
    num_rest = sum(1 for nm in cols if re.fullmatch(r"f_rest_\d+", nm))
    if num_rest % 3:
        raise ValueError(f"{source}: {num_rest} f_rest_* properties is not a multiple of 3")
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"rot_{j}" for j in range(4)]
    stack(required)  # one error listing everything that is missing
    means = stack(["x", "y", "z"])
    n = means.shape[0]
    rest = stack([f"f_rest_{j}" for j in range(num_rest)]) if num_rest else torch.zeros(n, 0)
    shN = rest.reshape(n, 3, num_rest // 3).transpose(1, 2).contiguous()
    standard = {"x", "y", "z", "nx", "ny", "nz", "opacity"} | {f"f_dc_{c}" for c in range(3)} \
        | {f"f_rest_{j}" for j in range(num_rest)} | {f"scale_{j}" for j in range(num_scales)} \
        | {f"rot_{j}" for j in range(4)}
    groups: Dict[str, int] = {}
    for nm in cols:
        m = re.fullmatch(r"([A-Za-z_]\w*?)_(\d+)", nm)
        if nm not in standard and m:
            groups[m.group(1)] = max(groups.get(m.group(1), 0), int(m.group(2)) + 1)
    for g, c in groups.items():  # a gap would make `stack` list every missing name: c can be huge in a bad file
        present = sum(1 for nm in cols if re.fullmatch(rf"{re.escape(g)}_\d+", nm) and nm not in standard)
        if present != c:
            raise ValueError(f"{source}: extra properties {g}_* are not numbered 0..{present - 1} (highest {c - 1})")
    extras = {g: stack([f"{g}_{j}" for j in range(c)]) for g, c in groups.items()}
    try:
        model = cls(means, stack([f"scale_{j}" for j in range(num_scales)]), stack([f"rot_{j}" for j in range(4)]),
                    stack(["opacity"])[:, 0], stack([f"f_dc_{c}" for c in range(3)])[:, None, :], shN, extras=extras)
    except ValueError as exc:  # non-finite values, an SH count that is no degree, ...: say which file
        raise ValueError(f"{source}: {exc}") from exc
    model.active_sh_degree = model.max_sh_degree
    return model.to(device) if device is not None else model
