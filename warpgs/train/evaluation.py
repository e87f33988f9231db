"""Held-out evaluation of a run: which views, the LPIPS net (built without shifting the training RNG), the metrics,
the PNG renders, and the history of the periodic evaluations."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Callable, List, Optional

import torch

from warpgs.metrics.image import LPIPSMetric
from warpgs.metrics.views import evaluate_views, summarize_views

if TYPE_CHECKING:
    from warpgs.config.schema import EvalConfig


class Evaluator:
    """Owns the evaluation views (chosen once), the LPIPS net and `history`, one entry per periodic evaluation.

    `render(view) -> rgb [H, W, 3]` renders the current model (the trainer's render with its extensions);
    `views`, when given, is a TrainViews whose kept device copies are reused instead of loading a view again.
    `ranks` (a distributed run's Ranks): each rank scores a contiguous share of the views and writes their PNGs;
    the scores are gathered, so every rank returns the same metrics, averaged in view order as one process does.
    `render_round(cameras) -> rgb` (model-parallel training, where a render needs every rank): renders one view per
    rank together and returns this rank's; the ranks then go through their shares in rounds (one whose share is
    used up renders a stand-in view and drops it), and `render` is not used."""

    def __init__(self, scene, config: EvalConfig, device, out_dir, *, render: Callable, views=None, ranks=None,
                 render_round: Optional[Callable] = None):
        if not callable(render):
            raise ValueError(f"render: expected a callable view -> rgb, got {render!r}")
        self.scene, self.config, self.device = scene, config, torch.device(device)
        self.out_dir = Path(out_dir)
        self.render = render
        self.views = views
        self.ranks = ranks
        self.render_round = render_round
        self._rounds: Optional[_Rounds] = None  # during a round-wise evaluation
        self.history: List[dict] = []
        self._chosen: Optional[tuple] = None  # (split, views) of evaluate()
        self._lpips: Optional[LPIPSMetric] = None

    def eval_views(self, split: Optional[str] = None) -> tuple:
        """(split actually used, views): the test views, or the training views when there are none."""
        split = split or self.config.split
        idx = self.scene.test if split == "test" else self.scene.train
        if not idx:
            split, idx = "train", self.scene.train
        load = self.views.kept_or_new if self.views is not None else (lambda i: self.scene.view(i, self.device))
        return split, [load(i) for i in idx]

    def lpips(self) -> Optional[LPIPSMetric]:
        if not self.config.lpips:
            return None
        if self._lpips is None:
            with torch.random.fork_rng(devices=[]):  # building the net must not shift the training RNG
                self._lpips = LPIPSMetric(self.config.lpips_net, device=self.device)
        return self._lpips

    def evaluate(self, *, save_images: bool = False, max_views: int = 0, keep_images: int = 0) -> dict:
        """Metrics of evaluate_views plus "split"; keep_images > 0 adds "images" {name: rgb [H,W,3] on the CPU,
        clamped to [0, 1]} of the first that many views (for TensorBoard), from the same renders."""
        shared = self.ranks is not None and self.ranks.enabled
        if shared:  # rank 0's log decides (the others log nothing but render their share of the images)
            keep_images = self.ranks.broadcast_object(keep_images, what="starting the evaluation")
        if self._chosen is None:
            self._chosen = self.eval_views()
        split, views = self._chosen
        if max_views:
            views = views[:max_views]
        save_dir = self.out_dir / "renders" / split if save_images else None
        images = {}

        def render(view):
            rgb = self.render(view) if self._rounds is None else self._rounds.next(view)
            if len(images) < keep_images:
                images[view.name] = rgb.detach().clamp(0.0, 1.0).cpu()
            return rgb

        if shared:
            metrics = self._evaluate_shared(render, views, save_dir, images)
        else:
            metrics = evaluate_views(render, views, lpips=self.lpips(), save_dir=save_dir)
        metrics["split"] = split
        if keep_images:
            metrics["images"] = dict(list(images.items())[:keep_images])
        return metrics

    def _evaluate_shared(self, render: Callable, views: list, save_dir, images: dict) -> dict:
        """evaluate_views over the ranks: this rank's share, then everyone's per-view scores (and kept images)."""
        lpips = self.lpips()
        mine = views[self.ranks.shard(len(views))]
        self._rounds = _Rounds(self.render_round, self.ranks, views) if self.render_round is not None else None
        try:
            if mine:
                per_view = evaluate_views(render, mine, lpips=lpips, save_dir=save_dir)["per_view"]
            else:  # fewer views than ranks
                per_view = {}
            if self._rounds is not None:
                self._rounds.finish()
        finally:
            self._rounds = None
        gathered = self.ranks.all_gather_object((per_view, images), what="gathering the evaluation scores")
        scores, kept = {}, {}
        for rank_scores, rank_images in gathered:
            scores.update(rank_scores)
            kept.update(rank_images)
        per_view = {v.name: scores[v.name] for v in views if v.name in scores}  # view order, as one process
        out = summarize_views(per_view, lpips)
        images.clear()
        images.update({v.name: kept[v.name] for v in views if v.name in kept})
        return out

    def periodic(self, step: int, num_primitives: int, train_seconds: float, *, keep_images: int = 0) -> tuple:
        """Evaluate at most eval.max_views views during training and append the entry to `history`;
        returns (entry, the metrics evaluate() gave)."""
        m = self.evaluate(max_views=self.config.max_views, keep_images=keep_images)
        entry = {"step": step, "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"],
                 "num_primitives": num_primitives, "train_seconds": round(train_seconds, 3)}
        self.history.append(entry)
        return entry, m

    # The checkpoint key of checkpoints written before this class existed.
    def state_dict(self) -> dict:
        return {"history": self.history}

    def load_state_dict(self, state: dict) -> None:
        self.history = list(state.get("history", []))


def scores_over_ranks(views: list, render: Callable, score: Callable, ranks=None,
                      render_round: Optional[Callable] = None, what: str = "gathering the scores") -> List[float]:
    """[score(render(view), view) for view in views], the renders shared out over the ranks (each renders its
    contiguous share; with render_round, model-parallel, in rounds of one view per rank) and the scores gathered,
    so every rank returns the same list, in view order, as one process computes it. A score may be a 0-d device
    tensor: the scores are read back together (one host read, not one a view that holds up the next render)."""
    if ranks is None or not ranks.enabled:
        return _floats([score(render(v), v) for v in views])
    share = range(len(views))[ranks.shard(len(views))]
    rounds = _Rounds(render_round, ranks, views) if render_round is not None else None
    values = [score(rounds.next(views[k]) if rounds is not None else render(views[k]), views[k]) for k in share]
    if rounds is not None:
        rounds.finish()
    mine = dict(zip(share, _floats(values)))
    merged = {}
    for part in ranks.all_gather_object(mine, what=what):
        merged.update(part)
    return [merged[k] for k in range(len(views))]


def _floats(values: list) -> List[float]:
    """Python floats of numbers or 0-d tensors, with one device read for the tensors."""
    if values and all(isinstance(v, torch.Tensor) for v in values):
        return torch.stack(values).tolist()
    return [float(v) for v in values]


class _Rounds:
    """The evaluation's renders in rounds of one view per rank (Evaluator's render_round): round k is the k-th
    view of every rank's share; a rank whose share is used up renders the first view again and drops it, so every
    rank makes the same number of round renders in the same order."""

    def __init__(self, render_round: Callable, ranks, views: list):
        self.render_round, self.rank = render_round, ranks.rank
        self.shares = [views[ranks.shard_of(len(views), r)] for r in range(ranks.world_size)]
        self.count, self.stand_in = max(len(s) for s in self.shares), views[0]
        self.done = 0

    def next(self, view):
        if self.shares[self.rank][self.done] is not view:
            raise RuntimeError(f"evaluation rounds: {view.name} out of turn")
        return self._render()

    def finish(self) -> None:
        while self.done < self.count:
            self._render()

    def _render(self):
        k = self.done
        cameras = [share[k] if k < len(share) else self.stand_in for share in self.shares]
        self.done += 1
        return self.render_round(cameras)
