"""Query maths without rendering: canonical-phrase relevancy, LangSplat normalisation, IoU / AP, and the CLIP
extra's clear errors when its packages or weights are missing."""
import math

import pytest
import torch

from warpgs.language.evaluate import average_precision, mask_iou
from warpgs.language.query import normalise_relevancy, relevancy_scores


def test_relevancy_is_min_over_pairwise_softmax():
    torch.manual_seed(0)
    feats = torch.nn.functional.normalize(torch.randn(7, 16), dim=-1)
    pos = torch.nn.functional.normalize(torch.randn(16), dim=0)
    negs = torch.nn.functional.normalize(torch.randn(4, 16), dim=-1)
    rel = relevancy_scores(feats, pos, negs, temperature=10.0)
    for i in range(7):
        pairs = [torch.softmax(10.0 * torch.stack([feats[i] @ pos, feats[i] @ n]), 0)[0] for n in negs]
        assert float(rel[i]) == pytest.approx(float(min(pairs)), abs=1e-6)
    # the query itself is maximally relevant; relevancy is in (0, 1)
    assert float(relevancy_scores(pos[None], pos, negs)[0]) > float(rel.max())
    assert bool(((rel > 0) & (rel < 1)).all())


def test_normalisation_follows_langsplat():
    rel = torch.tensor([[0.2, 0.4], [0.6, 1.0]])
    valid = torch.tensor([[True, True], [True, False]])
    norm = normalise_relevancy(rel, valid)
    # over valid entries: (r - 0.2) / 0.4 -> [0, .5, 1] -> 2x - 1 -> [-1, 0, 1] -> clipped [0, 0, 1]; invalid -> 0
    assert torch.allclose(norm, torch.tensor([[0.0, 0.0], [1.0, 0.0]]))
    assert torch.equal(normalise_relevancy(rel, torch.zeros_like(valid)), torch.zeros_like(rel))


def test_iou_and_average_precision():
    a = torch.tensor([True, True, False, False])
    b = torch.tensor([True, False, True, False])
    assert mask_iou(a, b) == pytest.approx(1 / 3)
    assert mask_iou(torch.zeros(3, dtype=torch.bool), torch.zeros(3, dtype=torch.bool)) == 1.0
    scores = torch.tensor([0.9, 0.8, 0.7, 0.6])
    gt = torch.tensor([1, 0, 1, 0])
    assert average_precision(scores, gt) == pytest.approx((1 / 1 + 2 / 3) / 2)
    assert average_precision(torch.tensor([0.5, 0.5, 0.1]), torch.tensor([1, 0, 1])) == pytest.approx(
        0.5 * 0.5 + 0.5 * (2 / 3))  # a tie counts as one threshold
    assert average_precision(scores, torch.tensor([1, 1, 0, 0])) == 1.0
    assert math.isnan(average_precision(scores, torch.zeros(4)))


def test_clip_extra_fails_clearly_without_packages_or_weights(tmp_path, monkeypatch):
    import importlib.util

    from warpgs.language import clip
    from warpgs.language.text import build_text_encoder

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name in ("open_clip", "segment_anything") else real(name, *a))
    with pytest.raises(clip.ClipUnavailable, match=r"warpgs\[clip\]"):
        build_text_encoder("clip", checkpoint=tmp_path / "nope.bin")
    monkeypatch.setattr(clip, "_require", lambda module, package: object())
    with pytest.raises(clip.ClipUnavailable, match="never downloads"):
        clip.ClipModel("ViT-B-16", tmp_path / "missing.bin")
    with pytest.raises(clip.ClipUnavailable, match="no checkpoint"):
        clip.ClipModel("ViT-B-16", None)
    with pytest.raises(ValueError):
        build_text_encoder("bert")


def test_whole_level_segments_partition_largest_first():
    import numpy as np

    from warpgs.language.clip import masked_crop, whole_level_segments

    big = np.zeros((10, 10), bool)
    big[:, :] = True
    small = np.zeros((10, 10), bool)
    small[2:5, 2:5] = True
    segs = whole_level_segments([{"segmentation": small, "area": 9}, {"segmentation": big, "area": 100}],
                                (10, 10), min_area=5)
    assert len(segs) == 1 and segs[0].all()  # the small mask lies inside the whole object: dropped
    img = np.full((10, 10, 3), 200, np.uint8)
    crop = masked_crop(img, small)
    assert crop.size == (3, 3)
