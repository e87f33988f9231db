"""Proximity-guided unpooling (FSGS's idea, our own formulation): where a primitive's near neighbours are far
away, the space between them is under-covered, as it is after a start from a few views' sparse points. Each
primitive is linked to its k nearest others; for every link longer than a distance threshold a new primitive is
placed at the link's midpoint, so gaps fill from what surrounds them instead of waiting for a gradient there.

The new primitive takes the two ends' mean colour and log-scales, the fainter end's opacity (a new primitive
should not occlude what the views already explain) and the first end's orientation and view-dependent colour.
Links are undirected (each pair once); the longest links come first when the budget cannot take them all."""
from __future__ import annotations

import torch

from warpgs.model.gaussians import knn
from warpgs.train.few_views import FewViewsRule

# strategy.unpool_every=auto: off with at most AUTO_OFF_MAX_VIEWS training views, at every refine with more. Measured
# against the sparse_llff preset without it (H200, paired by seed; docs/sparse_view.md): 7 real LLFF scenes at 3 views
# -0.16 +- 0.04 dB (it fills the budget with midpoints the three views cannot check), at 4 views a tie (+0.01 +- 0.11,
# 2 seeds), at 6 views +0.43 +- 0.03; 360° captures at 12 views +0.24 +- 0.06 (phone64) and +0.10 +- 0.08
# (bonsai800), at 24 views +0.13 +- 0.10 and +0.14 +- 0.05; a real 3x3 light field's 9 views +1.09 +- 0.07 (chess).
AUTO_OFF_MAX_VIEWS = 4
RULE = FewViewsRule("unpooling", "strategy.unpool_every", AUTO_OFF_MAX_VIEWS, 0, more=1)


def unpool_every_for(setting, num_train_views: int) -> int:
    """The period in refines that strategy.unpool_every asks for with this many training views (0: off)."""
    return RULE.value(setting, num_train_views, int)


def unpool_note(setting, every: int, num_train_views: int) -> str:
    """The start line's words on unpooling: on when on, why not when "auto" left it off, else ""."""
    return RULE.note(setting, every, num_train_views, "; unpooling" + (f" every {every} refines" if every > 1 else ""))


# Parameters the midpoint takes as the mean of the two ends (the rest come from the first end, except opacity).
MEAN_OF_ENDS = ("means", "log_scales", "sh0")


@torch.no_grad()
def midpoint_rows(params: dict, k: int, min_distance: float, room: int) -> dict:
    """{name: [M, ...] rows} of the new primitives (M <= room) for a model's parameter dict (`model.params`)."""
    means = params["means"].detach()
    n = means.shape[0]
    if n < 2 or room <= 0:
        return {name: p.detach()[:0] for name, p in params.items()}
    dist, idx = knn(means, k)
    src = torch.arange(n, device=means.device)[:, None].expand_as(idx)
    long = dist > min_distance
    a, b, d = src[long], idx[long], dist[long]
    # One link per unordered pair: a pair found from both ends is kept once (both ends measure the same length).
    key, inverse = torch.unique(torch.minimum(a, b) * n + torch.maximum(a, b), return_inverse=True)
    d = d.new_empty(len(key)).scatter_(0, inverse, d)
    a, b = key // n, key % n
    if len(d) > room:
        keep = torch.argsort(d, descending=True, stable=True)[:room]
        a, b = a[keep], b[keep]
    rows = {}
    for name, p in params.items():
        p = p.detach()
        if name in MEAN_OF_ENDS:
            rows[name] = 0.5 * (p[a] + p[b])
        elif name == "logit_opacities":
            rows[name] = torch.minimum(p[a], p[b])
        else:
            rows[name] = p[a].clone()
    return rows

