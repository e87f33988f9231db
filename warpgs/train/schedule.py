"""When a run densifies, resets opacities and stops.

**Fixed step counts** (`train.steps=N`): the run's tail is left alone (DensifySchedule below; DensifyStrategy
asks it):
  - densification (refines and the statistics for them) ends at min(refine_stop, refine_stop_fraction x N), with
    refine_stop_fraction 0.5 in the `gaussians` preset (the library default, 1, leaves refine_stop alone for the
    configs that set their own schedule, e.g. short test runs that densify to their end). 3DGS
    densifies for the first half of its 30k steps; the same half of a 3000-step run is 1500 steps, so a short run
    no longer densifies up to its last refine and is scored before its newest primitives have settled;
  - an opacity reset at step s happens only while densifying (s < that stop: the refines after a reset prune what
    stayed faint) and with a whole reset interval of training after it (s + reset_every <= N: the opacities grow
    back before the end; with refine_stop_fraction <= 0.5 the first condition implies it). A run of at most
    reset_every / refine_stop_fraction steps (6000 with the preset) resets nothing; 7000 steps reset once, at 3000.
With the preset at 30k this is 3DGS's schedule unchanged (densify 500..15k, resets 3k..12k), and the other presets
keep theirs at their own lengths (sparse_llff_baseline: densify to 5000 of 10000, one reset at 3000).

**`train.steps=auto`** (the `gaussians` preset's default): AutoStop below decides when densification stops and when
training stops, from a validation split of the *training* views (every `schedule.val_nth`-th training view is held
out; the test views are never read), scored every `schedule.val_every` steps. Why: on captures of a few dozen views
held-out PSNR peaks at 2–7k steps and falls by 0.5–3 dB by 30k while densification grows the model (phone64,
beer; docs/real_captures.md), while a large capture (bonsai800) still improves at 30k; a fixed length is right for
one kind only. The rule, with patience P, settle S and min_gain g (dB):
  1. densify as a fixed run of schedule.max_steps steps does (to refine_stop_fraction of it: 10k of the preset's
     20k); each validation score more than g above the best so
     far is the new best;
  2. stop densifying when the best is P steps old, except within S steps after an opacity reset (the reset's
     dip is not a plateau) and while the latest score rose by more than g since the one before
     (`wait_while_rising`: bonsai800's 255 views climb back from a reset for longer than P); the schedule's own
     densification stop also ends this phase;
  3. then train without densifying; stop when there has been no new best for P steps since the later of the
     best and the densification stop (non-densifying training gets P steps to beat the best); with
     `window_trend` (on in the preset), not while a best under 2P steps old has the mean of the last P steps'
     scores above the mean of the P steps before by more than g (a slow rise hidden in the scores' scatter);
  4. at that stop, when the latest score is more than g below the best, the run goes back to the state of the
     best score (`schedule.keep_best`; train/best_state.py keeps a copy of it);
  5. polish: the validation views go back into the training views for `schedule.polish` steps (no densification,
     no more validation), so the final model has seen every training view; then the run ends.
  The run never exceeds schedule.max_steps (polish included). Until densification stops the position learning
  rate follows the bounded run's decay (a fixed run of max_steps at the same step); from there it anneals
  log-linearly to its final value over P + polish steps from the later of that stop and the newest best
  (`anneal_follows_best`), the earliest the run can end, as a fixed run anneals over its own length
  (on beer's half, CPU, a fixed 3000-step run still gained 1.4 dB in its annealed last half while the auto run's
  lr, still on the bounded decay, gained nothing: docs/real_captures.md). The best state is kept (step 4): on
  phone64 the test PSNR fell 0.65-0.92 dB after the best validation score and did not come back by the stop.
Every validation and decision is logged (log.jsonl `type` "validation" / "schedule", the console) and listed in
metrics.json's "schedule". AutoStop's state goes into checkpoints with the strategy's (DensifyStrategy.state_dict),
whose `schedule` (a DensifySchedule) holds it.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Callable, List, Optional, Sequence, Tuple

DENSIFY, TRAIN, POLISH, DONE = "densify", "train", "polish", "done"


@dataclass
class ScheduleConfig:
    """The `schedule` section: the rule of `train.steps=auto` (module doc)."""
    # never more steps than this (polish included); the position lr decays over it. The gaussians preset: 20k, with
    # refine_stop_fraction 0.5 (densifying to 10k) and a 5000-step polish, as measured (docs/real_captures.md)
    max_steps: int = 30_000
    val_nth: int = 8  # every this-many-th training view is held out for validation (at least one)
    val_every: int = 500  # score the validation views every this many steps
    patience: int = 2000  # steps without a new best before densification (then training) stops
    min_gain: float = 0.02  # dB over the best that counts as a new best
    settle: int = 1000  # no densification decision within this many steps after an opacity reset
    polish: int = 1000  # final steps with the validation views trained on too (0: they stay held out)
    keep_best: bool = True  # at the stop, go back to the best validated state if the latest is worse (best_state.py)
    # A score that rose by more than min_gain since the previous one is not a plateau: no stop while it rises (a
    # large capture climbs back from an opacity reset's dip for more than `patience` steps)
    wait_while_rising: bool = True
    # The position lr's anneal after densification stops ends at the earliest end of the run: patience + polish
    # after the densification stop (false), or after the later of that stop and the newest best (true: a run that
    # keeps finding new bests keeps a decaying lr instead of training at the final one)
    anneal_follows_best: bool = True
    # No training stop while the best is under 2 x patience steps old and the mean of the last `patience` steps'
    # scores beats the mean of the `patience` steps before by more than min_gain. A capture that still improves
    # slowly (bonsai800 after 15k: about 0.05 dB a 1000 steps, its 32 views' scores scattered by as much) can go
    # 2000 steps without a single score beating the best by min_gain, and stopped there in 3 runs of 3 (0.45 dB under
    # gsplat's best); the windows' means see the rise. Replayed on 22 recorded runs, it changes those and one
    # early-peaking run (docs/real_captures.md).
    window_trend: bool = True

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type in ("bool", bool):  # the switches (keep_best, wait_while_rising, anneal_follows_best)
                if not isinstance(v, bool):
                    raise ValueError(f"{f.name}: expected true or false, got {v!r}")
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0 or v != v:
                raise ValueError(f"{f.name}: expected a non-negative number, got {v!r}")
        for name in ("max_steps", "val_nth", "val_every", "patience"):
            if int(getattr(self, name)) != getattr(self, name) or getattr(self, name) < 1:
                raise ValueError(f"{name}: expected a positive integer, got {getattr(self, name)!r}")
        for name in ("settle", "polish"):
            if int(getattr(self, name)) != getattr(self, name):
                raise ValueError(f"{name}: expected an integer, got {getattr(self, name)!r}")
        if self.val_nth < 2:
            raise ValueError(f"val_nth: expected >= 2 (1 would hold out every training view), got {self.val_nth}")
        if self.polish >= self.max_steps:
            raise ValueError(f"polish: {self.polish} steps do not fit in max_steps={self.max_steps}")


def validation_split(train: Sequence[int], nth: int) -> Tuple[List[int], List[int]]:
    """(kept training indices, validation indices): every nth training view from the middle of the first
    stretch (so not the views next to an LLFF every-8th test view), at least one; a clear error when too few views
    are left to train on."""
    train = list(train)
    if len(train) < 3:
        raise ValueError(f"train.steps=auto: needs at least 3 training views (it holds some out for validation), "
                         f"the scene has {len(train)}; give a step count instead")
    start = min(nth // 2, len(train) - 1)
    val = train[start::nth] or [train[len(train) // 2]]
    held = set(val)
    return [i for i in train if i not in held], val


class AutoStop:
    """The decisions of `train.steps=auto` (module doc) from a series of validation scores. Pure bookkeeping: the
    loop scores the views and applies what `observe` / `check_bound` return. State: phase, best score and step,
    the step densification stopped at, the polish's start and the run's end, and the scores and decisions so far."""

    def __init__(self, config: ScheduleConfig):
        self.config = config
        self.phase = DENSIFY
        self.best_psnr: Optional[float] = None
        self.best_step: Optional[int] = None
        self.densify_stop: Optional[int] = None  # step at which densification stopped (None: still on)
        self.polish_start: Optional[int] = None
        self.end: Optional[int] = None  # the run's last step count once decided
        self.scores: List[dict] = []  # {"step", "psnr"}
        self.decisions: List[dict] = []

    @property
    def validating(self) -> bool:
        return self.phase in (DENSIFY, TRAIN)

    def due(self, step: int) -> bool:
        """Whether the validation views are scored after `step` steps."""
        return self.validating and step > 0 and step % int(self.config.val_every) == 0

    def observe(self, step: int, psnr: float, *, last_reset: Optional[int] = None,
                scheduled_stop: Optional[int] = None) -> List[dict]:
        """One validation score after `step` steps. last_reset: the latest opacity reset at or before it (None:
        none); scheduled_stop: the step the schedule alone ends densification at. Returns the decisions taken."""
        cfg = self.config
        self.scores.append({"step": int(step), "psnr": float(psnr)})
        if self.best_psnr is None or psnr > self.best_psnr + cfg.min_gain:
            self.best_psnr, self.best_step = float(psnr), int(step)
        out = []
        if self.phase == DENSIFY:
            if scheduled_stop is not None and step >= scheduled_stop:
                out.append(self._stop_densifying(step, psnr, f"the densification schedule ended at step "
                                                             f"{scheduled_stop}"))
            elif last_reset is not None and step - last_reset <= cfg.settle:
                pass  # the dip after a reset is the reset's
            elif step - self.best_step >= cfg.patience and not self._rising():
                out.append(self._stop_densifying(step, psnr, self._stale(step)))
        elif (self.phase == TRAIN and step - max(self.best_step, self.densify_stop) >= cfg.patience
              and not self._rising() and not self._window_rising(step)):
            out.append(self._start_polish(step, psnr, self._stale(step) + f"; densification stopped at step "
                                                                          f"{self.densify_stop}"))
        return out

    def check_bound(self, step: int) -> List[dict]:
        """After every step: polish in time to end at schedule.max_steps, and end the polish. Returns decisions."""
        cfg = self.config
        if self.validating and step >= cfg.max_steps - cfg.polish:
            last = self.scores[-1]["psnr"] if self.scores else None
            return [self._start_polish(step, last, f"reached the bound: schedule.max_steps={cfg.max_steps}"
                                                    + (f" with {cfg.polish} polish steps" if cfg.polish else ""))]
        if self.phase == POLISH and step >= self.end:
            self.phase = DONE
        return []

    def means_lr(self, step: int, lr_at: Callable[[int], float]) -> Optional[float]:
        """The position learning rate at `step` once densification has stopped (None before: the bounded schedule
        `lr_at(step)` holds): log-linear from lr_at(densify stop) to lr_at(max_steps), the final value, over
        patience + polish steps (with anneal_follows_best: up to patience + polish after the later of the stop and
        the newest best), then that final value."""
        if self.densify_stop is None:
            return None
        start = int(self.densify_stop)
        span = max(int(self.config.patience) + int(self.config.polish), 1)
        if self.config.anneal_follows_best and self.best_step is not None:  # (a new best lifts the lr a little)
            span = min(span + max(int(self.best_step) - start, 0), max(int(self.config.max_steps) - start, 1))
        u = min(max((step - start) / span, 0.0), 1.0)
        return lr_at(start) ** (1.0 - u) * lr_at(int(self.config.max_steps)) ** u

    def finished(self, step: int) -> bool:
        return self.end is not None and step >= self.end

    def summary(self) -> dict:
        """For metrics.json: the outcome, every decision and every validation score."""
        return {"rule": "auto", "densify_stop": self.densify_stop, "polish_start": self.polish_start,
                "end": self.end, "best_validation_psnr": self.best_psnr, "best_step": self.best_step,
                "decisions": list(self.decisions), "validation": list(self.scores)}

    # ----- checkpoints (plain values: they travel inside the strategy's state) -----
    _KEYS = ("phase", "best_psnr", "best_step", "densify_stop", "polish_start", "end", "scores", "decisions")

    def state_dict(self) -> dict:
        return {k: getattr(self, k) for k in self._KEYS}

    def load_state_dict(self, state: dict) -> None:
        for k in self._KEYS:
            setattr(self, k, state[k])
        self.scores, self.decisions = list(self.scores), list(self.decisions)

    # ----- internals -----
    def _rising(self) -> bool:
        """With wait_while_rising: whether the latest score beat the one before by more than min_gain."""
        if not self.config.wait_while_rising or len(self.scores) < 2:
            return False
        return self.scores[-1]["psnr"] > self.scores[-2]["psnr"] + self.config.min_gain

    def _window_rising(self, step: int) -> bool:
        """With window_trend: whether a recent best's neighbourhood still rises (the mean of the scores of the last
        patience steps over those of the patience steps before, by more than min_gain)."""
        cfg = self.config
        if not cfg.window_trend or step - self.best_step >= 2 * cfg.patience:
            return False
        last = [s["psnr"] for s in self.scores if step - cfg.patience < s["step"] <= step]
        before = [s["psnr"] for s in self.scores if step - 2 * cfg.patience < s["step"] <= step - cfg.patience]
        if not last or not before:
            return False
        return sum(last) / len(last) > sum(before) / len(before) + cfg.min_gain

    def _stale(self, step: int) -> str:
        return (f"validation PSNR has not beaten its best {self.best_psnr:.2f} dB (step {self.best_step}) by "
                f"{self.config.min_gain:g} dB for {step - self.best_step} steps (patience {self.config.patience})")

    def _record(self, step: int, decision: str, psnr: Optional[float], reason: str) -> dict:
        entry = {"step": int(step), "decision": decision, "reason": reason,
                 "validation_psnr": None if psnr is None else float(psnr), "best_psnr": self.best_psnr,
                 "best_step": self.best_step}
        self.decisions.append(entry)
        return entry

    def _stop_densifying(self, step: int, psnr: float, reason: str) -> dict:
        self.phase, self.densify_stop = TRAIN, int(step)
        return self._record(step, "stop_densifying", psnr, reason)

    def _start_polish(self, step: int, psnr: Optional[float], reason: str) -> dict:
        if self.densify_stop is None:
            self.densify_stop = int(step)
        self.polish_start = int(step)
        self.end = min(int(step) + int(self.config.polish), int(self.config.max_steps))
        self.phase = POLISH if self.end > step else DONE
        what = (f"; the validation views join training for {self.end - step} polish steps" if self.end > step
                else "")
        return self._record(step, "stop", psnr, reason + what + f"; the run ends at step {self.end}")


class DensifySchedule:
    """When densification (refines, resets, statistics) runs and opacities reset: a fixed run's tail (module doc)
    and, with train.steps=auto, the AutoStop's earlier stop. config: the strategy's (refine_stop,
    refine_stop_fraction, reset_every); run_steps: the run's length (None: unknown, refine_stop alone)."""

    def __init__(self, config, run_steps: Optional[int] = None):
        self.config = config
        self.run_steps = None if run_steps is None else int(run_steps)
        self.auto: Optional[AutoStop] = None  # set by the trainer with train.steps=auto

    def scheduled_stop(self) -> int:
        """The step at which densification ends by the schedule alone: refine_stop, or sooner, at
        refine_stop_fraction of the run when its length is known."""
        stop = int(self.config.refine_stop)
        if self.run_steps is not None:
            stop = min(stop, int(self.config.refine_stop_fraction * self.run_steps))
        return stop

    def refine_stop_at(self) -> int:
        """The step at which densification (refines, resets, statistics) ends: the schedule's, or the auto rule's
        decision when it came sooner."""
        stop = self.scheduled_stop()
        if self.auto is not None and self.auto.densify_stop is not None:
            stop = min(stop, int(self.auto.densify_stop))
        return stop

    def densifying(self, step: int) -> bool:
        """Whether this step gathers statistics and may refine or reset."""
        return step < self.refine_stop_at()

    def resets_at(self, step: int) -> bool:
        """An opacity reset at this step: on the reset_every grid, while densifying (the refines after it prune what
        stayed faint), and with a whole interval of training after it before the run ends (the opacities grow
        back; with refine_stop_fraction <= 0.5 the quiet tail already guarantees it)."""
        every = int(self.config.reset_every)
        if not every or step <= 0 or step % every or step >= self.refine_stop_at():
            return False
        return self.run_steps is None or step + every <= self.run_steps

    def last_reset(self, step: int) -> Optional[int]:
        """The latest step <= `step` the schedule resets opacities at (None: none yet)."""
        every = int(self.config.reset_every)
        if not every:
            return None
        for s in range(step - step % every, 0, -every):
            if self.resets_at(s):
                return s
        return None
