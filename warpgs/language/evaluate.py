"""Query accuracy against labelled masks: IoU of thresholded masks and average precision of relevancy scores.

For every evaluation view with a label map and every label present in it (at least `min_pixels` pixels), the
label's name is the text query; the ground truth is `labels == id`. mIoU and mAP are means over these
(view, query) pairs, as in LERF/LangSplat-style evaluations.
"""
from __future__ import annotations

import math
from typing import Dict, Iterable, Optional

import numpy as np
import torch


def mask_iou(pred, gt) -> float:
    """IoU of two boolean masks; 1.0 when both are empty."""
    p = torch.as_tensor(pred).bool()
    g = torch.as_tensor(gt).bool().to(p.device)
    union = int((p | g).sum())
    return 1.0 if union == 0 else int((p & g).sum()) / union


def average_precision(scores, gt) -> float:
    """Area under the precision-recall curve, sum_n (R_n - R_{n-1}) P_n over distinct score thresholds
    (ties handled as one threshold, like scikit-learn's average_precision_score). NaN without positives."""
    s = torch.as_tensor(scores).reshape(-1).double()
    g = torch.as_tensor(gt).reshape(-1).bool().to(s.device)
    n_pos = int(g.sum())
    if n_pos == 0:
        return math.nan
    order = torch.argsort(s, descending=True, stable=True)
    s, g = s[order], g[order].double()
    tp = torch.cumsum(g, 0)
    fp = torch.cumsum(1.0 - g, 0)
    # last index of each run of equal scores = one threshold
    last = torch.ones_like(s, dtype=torch.bool)
    last[:-1] = s[1:] != s[:-1]
    tp, fp = tp[last], fp[last]
    precision = tp / (tp + fp)
    recall = tp / n_pos
    prev = torch.cat([recall.new_zeros(1), recall[:-1]])
    return float(((recall - prev) * precision).sum())


def evaluate_language(field, views: Iterable, label_names: Dict[int, str], *, threshold: Optional[float] = None,
                      min_pixels: int = 16, names: Optional[Iterable[str]] = None) -> dict:
    """{"miou", "map", "num_queries", "per_label": {name: {"iou", "ap", "n"}}, "per_query": [...]}.

    views: objects with .labels [H, W] ints (e.g. warpgs.data.View); names restricts the queried labels."""
    wanted = set(names) if names is not None else None
    rows = []
    for view in views:
        labels = getattr(view, "labels", None)
        if labels is None:
            continue
        labels = torch.as_tensor(labels).to(field.model.device)
        ids, counts = torch.unique(labels, return_counts=True)
        present = [int(i) for i, c in zip(ids.tolist(), counts.tolist())
                   if i != 0 and c >= min_pixels and int(i) in label_names]
        if wanted is not None:
            present = [i for i in present if label_names[i] in wanted]
        if not present:
            continue
        feats, surface, out = field.feature_map(view)
        for label in present:
            name = label_names[label]
            result = field._result(field.scores(feats, name), surface, out, threshold)
            gt = labels == label
            rows.append({"view": view.name, "query": name, "iou": mask_iou(result.mask, gt),
                         "ap": average_precision(result.relevancy, gt), "gt_pixels": int(gt.sum()),
                         "mask_pixels": int(result.mask.sum())})
    per_label: Dict[str, dict] = {}
    for r in rows:
        e = per_label.setdefault(r["query"], {"iou": [], "ap": []})
        e["iou"].append(r["iou"])
        e["ap"].append(r["ap"])
    summary = {k: {"iou": float(np.mean(v["iou"])), "ap": float(np.nanmean(v["ap"])), "n": len(v["iou"])}
               for k, v in per_label.items()}
    return {"miou": float(np.mean([r["iou"] for r in rows])) if rows else math.nan,
            "map": float(np.nanmean([r["ap"] for r in rows])) if rows else math.nan,
            "num_queries": len(rows), "threshold": field.threshold if threshold is None else float(threshold),
            "per_label": summary, "per_query": rows}
