"""The trainer's held-out evaluation: which views, the LPIPS net (built without shifting the RNG), metrics."""
from __future__ import annotations

from typing import Optional

import torch

from warpgs.metrics.views import evaluate_views
from warpgs.metrics.image import LPIPSMetric


class TrainerEvaluationMixin:
    """Part of `warpgs.train.trainer.Trainer` (uses its config, scene, views, device and render)."""

    # ----- evaluation -----------------------------------------------------------------------------------------
    def eval_views(self, split: Optional[str] = None) -> tuple:
        """(split actually used, views): the test views, or the training views when there are none."""
        split = split or self.config.eval.split
        idx = self.scene.test if split == "test" else self.scene.train
        if not idx:
            split, idx = "train", self.scene.train
        return split, [self.view(i) if i in self._views else self.scene.view(i, self.device) for i in idx]

    def lpips(self) -> Optional[LPIPSMetric]:
        if not self.config.eval.lpips:
            return None
        if self._lpips is None:
            with torch.random.fork_rng(devices=[]):  # building the net must not shift the training RNG
                self._lpips = LPIPSMetric(self.config.eval.lpips_net, device=self.device)
        return self._lpips

    def evaluate(self, *, save_images: bool = False, max_views: int = 0) -> dict:
        if self._eval_views is None:
            self._eval_views = self.eval_views()
        split, views = self._eval_views
        if max_views:
            views = views[:max_views]
        save_dir = self.out_dir / "renders" / split if save_images else None
        metrics = evaluate_views(lambda v: self.render(v, ("rgb",)).rgb, views, lpips=self.lpips(),
                                 save_dir=save_dir)
        metrics["split"] = split
        return metrics
