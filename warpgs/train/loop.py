"""The training loop: progress, periodic evaluation and checkpoints, Ctrl-C and NaN stops, the final outputs."""
from __future__ import annotations

import signal
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, List, Optional

import torch

from warpgs.utils.atomic_file import atomic_write_bytes
from warpgs.metrics.views import write_json
from warpgs.utils.progress import Progress
from warpgs.train.guard import NonFiniteError


@dataclass
class TrainResult:
    out_dir: Path
    steps: int
    loss: Optional[float]  # total loss of the last step
    metrics: dict
    train_seconds: float
    num_primitives: int
    history: List[dict] = field(default_factory=list)


class TrainingLoopMixin:
    """Part of `warpgs.train.trainer.Trainer` (runs its train_step, evaluate and save_checkpoint)."""

    # ----- the loop -------------------------------------------------------------------------------------------
    def _say(self, progress: Optional[Progress], message: str) -> None:
        if self.quiet:
            return
        if progress is not None:
            progress.write(message)
        else:
            print(message, file=sys.stderr)

    def fit(self) -> TrainResult:
        threads = self.config.train.threads or (1 if self.device.type == "cpu" else 0)
        previous = torch.get_num_threads()
        if threads:
            # On CPU the Warp kernels spread over their own thread pool; torch's OpenMP workers spinning next to
            # them (and next to any other process) cost far more than they save on these small per-image ops:
            # measured on the 2-core machine with another job running, 0.06-0.15 s a step with 1 thread against
            # 0.7 s with 2 (128x96, 3k Gaussians).
            torch.set_num_threads(threads)
        try:
            return self._fit()
        finally:
            torch.set_num_threads(previous)

    def _fit(self) -> TrainResult:
        cfg = self.config
        self.out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(self.out_dir / "config.yaml", cfg.to_yaml().encode())
        progress = Progress(self.max_steps, self.step, enabled=cfg.train.progress and not self.quiet,
                            log_every=cfg.train.log_every)
        if self.step == 0 or self.init_source != "checkpoint":
            self._say(progress, f"warpgs: {self.scene.summary()}")
            self._say(progress, f"warpgs: {self.model.num_primitives} {self.model.kind} from {self.init_source}; "
                                f"losses {[t.name for t in self.terms]} render {list(self.outputs)}; "
                                f"{self.max_steps} steps on {self.device}; output {self.out_dir}")
        else:
            self._say(progress, f"warpgs: resuming at step {self.step} from {self.checkpoint_path}")
        ema_loss = ema_psnr = None
        try:
            with _StopOnSigint(lambda m: self._say(progress, m)) as sigint:
                while self.step < self.max_steps:
                    if sigint.requested:
                        raise KeyboardInterrupt
                    info = self.train_step()
                    for ext in self.extensions:
                        ext.after_step(self, info["step"], info)
                    ema_loss = info["loss"] if ema_loss is None else 0.9 * ema_loss + 0.1 * info["loss"]
                    if info["psnr"] is not None:
                        ema_psnr = info["psnr"] if ema_psnr is None else 0.9 * ema_psnr + 0.1 * info["psnr"]
                    last = self.history[-1] if self.history else {}
                    progress.update(self.step, loss=ema_loss, psnr=ema_psnr, n=self.model.num_primitives,
                                    test=last.get("psnr"))
                    if cfg.eval.every and self.step % cfg.eval.every == 0 and self.step < self.max_steps:
                        self._periodic_eval(progress)
                    if (cfg.train.checkpoint_every and self.step % cfg.train.checkpoint_every == 0
                            and self.step < self.max_steps):
                        self.save_checkpoint()
        except KeyboardInterrupt:
            progress.close()
            if self._at_boundary and self.step != self._checkpoint_step:
                try:
                    self.save_checkpoint()
                    self._say(None, f"warpgs: interrupted; checkpoint at step {self.step} in "
                                    f"{self.checkpoint_path} (continue with --resume)")
                except KeyboardInterrupt:
                    self._say(None, "warpgs: interrupted again while saving; the previous checkpoint is intact")
            else:
                kept = (f"the checkpoint of step {self._checkpoint_step} in {self.checkpoint_path} is intact"
                        if self._checkpoint_step >= 0 else "no checkpoint was written yet")
                self._say(None, f"warpgs: interrupted during step {self.step}; {kept}")
            raise
        except NonFiniteError as e:
            progress.close()
            kept = (f"last good checkpoint: step {self._checkpoint_step} in {self.checkpoint_path}"
                    if self._checkpoint_step >= 0 else "no checkpoint was written")
            self._say(None, f"warpgs: stopped, {e}; {kept}")
            raise
        progress.close()
        return self.finish()

    def _periodic_eval(self, progress: Progress) -> None:
        m = self.evaluate(max_views=self.config.eval.max_views)
        entry = {"step": self.step, "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"],
                 "num_primitives": self.model.num_primitives, "train_seconds": round(self.train_seconds, 3)}
        self.history.append(entry)
        lp = f" lpips {m['lpips']:.4f}" if m["lpips"] is not None else ""
        self._say(progress, f"[eval {m['split']} @ {self.step}] psnr {m['psnr']:.2f} ssim {m['ssim']:.4f}{lp} "
                            f"n {self.model.num_primitives} ({self.train_seconds:.1f} s)")

    def finish(self) -> TrainResult:
        """Final checkpoint, PLY, test renders and metrics.json."""
        cfg = self.config
        if self.step != self._checkpoint_step:
            self.save_checkpoint()
        self.model.save_ply(self.out_dir / cfg.output.ply)
        m = self.evaluate(save_images=cfg.eval.save_images)
        metrics = {"split": m["split"], "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m["lpips"]}
        if "lpips_unavailable" in m:
            metrics["lpips_unavailable"] = m["lpips_unavailable"]
        metrics.update({"num_primitives": self.model.num_primitives, "steps": self.step,
                        "train_seconds": round(self.train_seconds, 3), "num_views": m["num_views"],
                        "model_kind": self.model.kind, "device": str(self.device), "scene": str(self.scene.root),
                        "final_loss": self.last_loss, "history": self.history, "per_view": m["per_view"]})
        write_json(self.out_dir / cfg.output.metrics, metrics)
        lp = f" lpips {m['lpips']:.4f}" if m["lpips"] is not None else " lpips unavailable"
        self._say(None, f"warpgs: {m['split']} psnr {m['psnr']:.2f} ssim {m['ssim']:.4f}{lp}; "
                        f"{self.model.num_primitives} primitives; {self.step} steps in {self.train_seconds:.1f} s")
        return TrainResult(self.out_dir, self.step, self.last_loss, metrics, self.train_seconds,
                           self.model.num_primitives, list(self.history))


class _StopOnSigint:
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
