"""The training loop: when things happen around Trainer.train_step (progress line, periodic evaluation and
checkpoints, the log, Ctrl-C and NaN stops) and the final outputs. What a step is and the state it changes
belong to the Trainer and its collaborators; the loop owns only its progress line and running means."""
from __future__ import annotations

import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, List, Optional

import torch

from warpgs.metrics.image import psnr
from warpgs.metrics.views import write_json
from warpgs.render.device_state import device_state
from warpgs.train import setup as train_setup
from warpgs.train.distributed import DistributedError
from warpgs.train.evaluation import scores_over_ranks
from warpgs.train.guard import NonFiniteError
from warpgs.train.dropout import dropout_note, manner_note
from warpgs.train.steps_by_views import steps_note
from warpgs.train.unpool import unpool_note
from warpgs.train.virtual_views import virtual_views_note
from warpgs.train.warm_up import compile_step_kernels
from warpgs.utils.atomic_file import atomic_write_bytes
from warpgs.utils.progress import Progress


@dataclass
class TrainResult:
    out_dir: Path
    steps: int
    loss: Optional[float]  # total loss of the last step
    metrics: dict
    train_seconds: float
    num_primitives: int
    history: List[dict] = field(default_factory=list)


class RunningMean:
    """Exponential moving average for the progress line: starts at the first value, then gives each new one
    `weight`; None values are skipped."""

    def __init__(self, weight: float = 0.1):
        if not 0.0 < weight <= 1.0:
            raise ValueError(f"weight: expected a value in (0, 1], got {weight!r}")
        self.weight = weight
        self.value: Optional[float] = None

    def update(self, x: Optional[float]) -> Optional[float]:
        if x is not None:
            self.value = x if self.value is None else (1.0 - self.weight) * self.value + self.weight * x
        return self.value


class TrainingLoop:
    """Runs one Trainer from its step to max_steps through its public parts (train_step, extensions, evaluator,
    checkpointer, log), then writes the final outputs. Built per fit(); owns the progress line and the running
    means shown on it."""

    def __init__(self, trainer):
        self.trainer = trainer
        self.progress: Optional[Progress] = None
        self.loss_mean, self.psnr_mean = RunningMean(), RunningMean()
        self.previous_info = None  # the last step's info, while its loss values may still be on the device

    def say(self, message: str) -> None:
        """A console line (above the progress line while it is shown); nothing when the trainer is quiet."""
        if self.trainer.quiet:
            return
        if self.progress is not None:
            self.progress.write(message)
        else:
            print(message, file=sys.stderr)

    def run(self) -> "TrainResult":
        tr, cfg = self.trainer, self.trainer.config
        tr.out_dir.mkdir(parents=True, exist_ok=True)
        if tr.ranks.is_main:  # a distributed run's files are rank 0's to write
            atomic_write_bytes(tr.out_dir / "config.yaml", cfg.to_yaml().encode())
        self.progress = Progress(tr.max_steps, tr.step, enabled=cfg.train.progress and not tr.quiet,
                                 log_every=cfg.train.log_every)
        if tr.step == 0 or tr.init_source != "checkpoint":
            self.say(f"warpgs: {tr.scene.summary()}")
            virtual = virtual_views_note(cfg.train.virtual_views, tr.virtual_every, len(tr.scene.train))
            virtual += dropout_note(cfg.train.drop_rate, tr.drop_rate, len(tr.scene.train))
            virtual += manner_note(cfg.train.drop_schedule, cfg.train.drop_near, tr.drop_rate)
            virtual += unpool_note(cfg.strategy.unpool_every, tr.strategy.config.unpool_every, len(tr.scene.train))
            self.say(f"warpgs: {tr.num_primitives} {tr.model.kind} from {tr.init_source}; "
                     f"losses {tr.loss_set.names} render {list(tr.outputs)}{virtual}; "
                     f"{self._length()} on {tr.device}; output {tr.out_dir}")
            if cfg.data.path is not None and not tr.quiet:  # once per training run: not on resume, render or eval
                train_setup.warn_pose_jumps(tr.scene, self.say)
        else:
            self.say(f"warpgs: resuming at step {tr.step} from {tr.checkpoint_path}")
        t0 = time.perf_counter()
        with tr.clock.stage("load_views"):
            loaded = tr.views.load_all()  # outside the steps' clock, as gsplat's and 3DGS's loaders do
        if loaded:
            self.say(f"warpgs: {loaded} training views loaded onto {tr.device} in {time.perf_counter() - t0:.1f} s")
        if tr.step < self.end():
            with tr.clock.stage("compile_kernels"), tr.lock:  # outside the steps' clock too (train/warm_up.py)
                compile_step_kernels(tr)
        self._pairs_at_start = speculative_pair_stats(tr)  # after the warm-up's render: the run's own count
        slow = {name: s for name, s in tr.clock.seconds.items() if s >= 1.0}
        if slow:  # where the wait before the first step went (triangulation and estimated priors are cached after)
            self.say("warpgs: set-up " + ", ".join(f"{name.replace('_', ' ')} {s:.1f} s" for name, s in slow.items()))
        if tr.strategy.schedule.auto is not None and tr.step > 0:  # a checkpoint written before the rule saw its step
            with tr.lock:  # (a step's hook or a second Ctrl-C stopped it): that step's validation and decisions
                self._auto_schedule()
        try:
            with StopOnSigint(self.say) as sigint:
                while tr.step < self.end():
                    if sigint.requested and not tr.ranks.enabled:
                        raise KeyboardInterrupt
                    # Distributed: the request travels with the step's gradients, so every rank stops after the
                    # same step (a rank stopping alone would leave the others waiting in a collective).
                    tr.stop_requested = sigint.requested
                    with tr.lock:  # a viewer thread renders between steps, never during one
                        self._one_step()
        except KeyboardInterrupt:
            self._close_progress()
            self._interrupted()
            raise
        except (NonFiniteError, DistributedError) as e:
            self._close_progress()
            last = tr.checkpointer.last_step
            kept = (f"last good checkpoint: step {last} in {tr.checkpoint_path}" if last >= 0
                    else "no checkpoint was written")
            self.say(f"warpgs: stopped, {e}; {kept}")
            raise
        self._close_progress()
        with tr.lock:
            return self.finish()

    def _one_step(self) -> None:
        tr, cfg = self.trainer, self.trainer.config
        info = tr.train_step()
        for ext in tr.extensions:
            ext.after_step(tr, info["step"], info)
        last = tr.history[-1] if tr.history else {}
        # The running means take each step's loss a step late when it is still on the device (a GPU step): by now
        # the previous step's values are on the host, and reading this step's would wait for its backward.
        shown, self.previous_info = (self.previous_info if info.pending else info), info
        if shown is not None:
            self.loss_mean.update(shown["loss"])
            self.psnr_mean.update(shown["psnr"])
        self.progress.update(tr.step, loss=self.loss_mean.value, psnr=self.psnr_mean.value, n=tr.num_primitives,
                             test=last.get("psnr"))
        if tr.strategy.schedule.auto is not None:  # before the log line, so a run that ends here logs its last step
            self._auto_schedule()
        end = self.end()
        if tr.log.due(tr.step, end):
            tr.log.train(tr.step, info, tr.learning_rates(), tr.train_seconds)
        if cfg.eval.every and tr.step % cfg.eval.every == 0 and tr.step < end:
            self._periodic_eval()
        if cfg.train.checkpoint_every and tr.step % cfg.train.checkpoint_every == 0 and tr.step < end:
            tr.save_checkpoint()
        if info.get("stop"):  # a rank got Ctrl-C: every rank stops at this same boundary
            raise KeyboardInterrupt

    def _length(self) -> str:
        tr = self.trainer
        if tr.strategy.schedule.auto is None:
            return steps_note(tr.config.train.steps, tr.max_steps, len(tr.scene.train))
        return (f"steps=auto (at most {tr.max_steps}; validation on {len(tr.views.held_out)} held-out training "
                f"views every {tr.config.schedule.val_every} steps)")

    def end(self) -> int:
        """The step count the run stops at: max_steps, or train.steps=auto's decided end."""
        auto = self.trainer.strategy.schedule.auto
        return auto.end if auto is not None and auto.end is not None else self.trainer.max_steps

    def _auto_schedule(self) -> None:
        """train.steps=auto (train/schedule.py): score the validation views when due, apply the rule's decisions
        (stop densifying; put the validation views back for the polish and fix the end), log them."""
        tr = self.trainer
        schedule, step = tr.strategy.schedule, tr.step
        auto = schedule.auto
        decisions = []
        if auto.due(step) and not (auto.scores and auto.scores[-1]["step"] >= step):  # once a step (resumes)
            with tr.clock.stage("validation"):  # the rule's own cost beside the steps: renders and best copies
                psnr = self._validation_psnr()
                tr.log.event("validation", step, {"psnr": psnr, "num_views": len(tr.views.held_out)},
                             train_seconds=tr.train_seconds)
                decisions += auto.observe(step, psnr, last_reset=schedule.last_reset(step - 1),
                                          scheduled_stop=schedule.scheduled_stop())
                if tr.best_state is not None and auto.best_step == step:  # a new best: copy it (train/best_state.py)
                    tr.best_state.capture(step, tr.training_state())
        decisions += auto.check_bound(step)
        for d in decisions:
            if d["decision"] == "stop":
                self._end_from_best(d)
                if auto.end > step:
                    d["views_restored"] = len(tr.views.restore_held_out())
            tr.log.event("schedule", step, d, train_seconds=tr.train_seconds)
            self.say(f"[schedule @ {step}] {d['decision'].replace('_', ' ')}: {d['reason']}")
        if decisions and self.progress is not None:
            self.progress.total = self.end()

    def _end_from_best(self, decision: dict) -> None:
        """At the rule's stop: go back to the best validated state when the latest score is more than min_gain
        below it (schedule.keep_best); the decision records the step gone back to. The copy is dropped either
        way: nothing is validated after the stop."""
        tr = self.trainer
        best, auto = tr.best_state, tr.strategy.schedule.auto
        if best is None or best.step is None:
            return
        latest = auto.scores[-1] if auto.scores else None
        if (latest is not None and best.step < tr.step
                and latest["psnr"] < auto.best_psnr - auto.config.min_gain):
            best.restore(tr.training_state())
            tr.count_primitives()
            decision["restored_step"] = best.step
            decision["reason"] += (f"; back to the state of step {best.step} (validation {auto.best_psnr:.2f} dB "
                                   f"against {latest['psnr']:.2f} dB now), {tr.num_primitives} primitives")
        best.load_state_dict(None)

    @torch.no_grad()
    def _validation_psnr(self) -> float:
        """Mean PSNR over the held-out training views (renders clamped to [0, 1], as evaluations score). The ranks
        share the renders out (model-parallel: in rounds, every rank's camera at once) and gather the scores, so all
        ranks get the value one process gets and take the same decisions."""
        tr = self.trainer
        views = [tr.views.kept_or_new(i) for i in tr.views.held_out]
        # psnr stays on the device: scores_over_ranks reads the scores back at once, not a view at a time.
        scores = scores_over_ranks(views, lambda v: tr.render(v, ("rgb",)).rgb,
                                   lambda rgb, v: psnr(rgb.clamp(0.0, 1.0), v.image), tr.ranks,
                                   tr._render_round if tr.model_parallel else None, what="the validation score")
        return sum(scores) / len(scores)

    def _close_progress(self) -> None:
        self.progress.close()
        self.progress = None  # later messages go straight to stderr

    def _interrupted(self) -> None:
        """Ctrl-C: checkpoint at the step boundary unless that step is on disk already, or say what is kept."""
        tr = self.trainer
        last = tr.checkpointer.last_step
        if tr.at_boundary and tr.step != last:
            try:
                tr.save_checkpoint()
                self.say(f"warpgs: interrupted; checkpoint at step {tr.step} in {tr.checkpoint_path} "
                         f"(continue with --resume)")
            except KeyboardInterrupt:
                self.say("warpgs: interrupted again while saving; the previous checkpoint is intact")
        else:
            kept = (f"the checkpoint of step {last} in {tr.checkpoint_path} is intact" if last >= 0
                    else "no checkpoint was written yet")
            self.say(f"warpgs: interrupted during step {tr.step}; {kept}")

    def _periodic_eval(self) -> None:
        tr = self.trainer
        with tr.clock.stage("periodic_evaluation"):
            entry, m = tr.evaluator.periodic(tr.step, tr.num_primitives, tr.train_seconds, keep_images=tr.log.images)
        tr.log.eval(tr.step, m, num_primitives=entry["num_primitives"], train_seconds=tr.train_seconds)
        lp = f" lpips {m['lpips']:.4f}" if m["lpips"] is not None else ""
        self.say(f"[eval {m['split']} @ {tr.step}] psnr {m['psnr']:.2f} ssim {m['ssim']:.4f}{lp} "
                 f"n {tr.num_primitives} ({tr.train_seconds:.1f} s)")

    def finish(self) -> "TrainResult":
        """Final checkpoint, PLY, test renders, metrics.json and the final log entry."""
        tr, cfg = self.trainer, self.trainer.config
        with tr.clock.stage("final_checkpoint_and_ply"):
            if tr.step != tr.checkpointer.last_step:
                tr.save_checkpoint()
            with tr.whole_model() as whole:  # train.parallel=model: the shards gathered (in CPU memory) for the file
                if tr.ranks.is_main:
                    whole.save_ply(tr.out_dir / cfg.output.ply)
        with tr.clock.stage("final_evaluation"):
            m = tr.evaluator.evaluate(save_images=cfg.eval.save_images, keep_images=tr.log.images)
        tr.log.eval(tr.step, m, num_primitives=tr.num_primitives, train_seconds=tr.train_seconds, final=True)
        metrics = {"split": m["split"], "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"]}
        if "lpips_unavailable" in m:
            metrics["lpips_unavailable"] = m["lpips_unavailable"]
        if tr.strategy.schedule.auto is not None:
            metrics["schedule"] = tr.strategy.schedule.auto.summary()
        if tr.phases.enabled:  # every rank's: a rank waiting in the all-reduce shows the others' extra work
            metrics["phases"] = tr.ranks.all_gather_object(tr.phases.summary(), what="gathering the phase times")
        if tr.device.type == "cuda":  # rank 0's peak (with train.parallel=model: one share's)
            metrics["peak_gpu_memory_bytes"] = int(torch.cuda.max_memory_allocated(tr.device))
        pairs = speculative_pair_stats(tr)
        if pairs["renders"] > self._pairs_at_start["renders"]:  # train.speculative_pairs ran: steps it skipped
            metrics["speculative_pairs"] = {k: pairs[k] - self._pairs_at_start[k] for k in ("renders", "skipped")}
        metrics.update({"num_primitives": tr.num_primitives, "steps": tr.step,
                        "train_seconds": round(tr.train_seconds, 3), "num_views": m["num_views"],
                        "model_kind": tr.model.kind, "device": str(tr.device), "scene": str(tr.scene.root),
                        "final_loss": tr.last_loss, "history": tr.history, "per_view": m["per_view"],
                        "stage_seconds": dict(tr.clock.seconds)})
        if tr.ranks.is_main:
            write_json(tr.out_dir / cfg.output.metrics, metrics)
        tr.ranks.barrier("waiting for rank 0 to write the final outputs")
        lp = f" lpips {m['lpips']:.4f}" if m["lpips"] is not None else " lpips unavailable"
        self.say(f"warpgs: {m['split']} psnr {m['psnr']:.2f} ssim {m['ssim']:.4f}{lp}; "
                 f"{tr.num_primitives} primitives; {tr.step} steps in {tr.train_seconds:.1f} s")
        return TrainResult(tr.out_dir, tr.step, tr.last_loss, metrics, tr.train_seconds,
                           tr.num_primitives, list(tr.history))


class StopOnSigint:
    """First Ctrl-C: finish the current step, then stop (the trainer checkpoints there). Second: abort now."""

    def __init__(self, say: Callable[[str], None]):
        self.say = say
        self.requested = False
        self._previous = None

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        self.say("warpgs: Ctrl-C: stopping after this step (press again to abort without saving)")

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            try:
                self._previous = signal.signal(signal.SIGINT, self._handler)
            except (ValueError, OSError):
                self._previous = None
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False


def speculative_pair_stats(trainer) -> dict:
    """This thread's speculative renders on the trainer's device so far and those whose pairs overflowed (each a
    skipped step; render/pair_room.py). Zero on the CPU unless tests force the path there."""
    stats = device_state(trainer.device).ws.pair_rooms.stats()
    return {"renders": stats["speculative_calls"], "skipped": stats["overflows"]}
