"""Training logs: `<out>/log.jsonl`, one JSON object a line for every logged step (every train.log_every steps and
the last) and every evaluation; with train.log=tensorboard also the same scalars and evaluation renders as
TensorBoard events under `<out>/tensorboard`. "step" is the number of steps done, as in the progress line,
the evaluation history and checkpoints. A resumed run drops the entries past its checkpoint and appends."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Dict, Optional

from warpgs.utils.atomic_file import atomic_write_bytes

LOG_FILE = "log.jsonl"
TENSORBOARD_DIR = "tensorboard"
KINDS = ("jsonl", "tensorboard", "none")
TENSORBOARD_IMAGES = 4  # evaluation views whose renders go to TensorBoard at each evaluation


class MissingExtraError(ModuleNotFoundError, ValueError):
    """An optional dependency is not installed (a ValueError too, so the CLI reports it like a bad config)."""


def summary_writer_class():
    """torch's SummaryWriter, or a MissingExtraError naming the extra that installs it."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError as e:
        raise MissingExtraError(f"train.log: 'tensorboard' needs the tensorboard package ({e}); install it with "
                                f"pip install 'warpgs[tensorboard]'", name="tensorboard") from None
    return SummaryWriter


class TrainLog:
    """Owns the open log file, the TensorBoard writer and the wall clock of one fit(). Built before training, so
    a missing tensorboard package stops the run before its first step; files open in open(start_step)."""

    def __init__(self, out_dir, *, kind: str = "jsonl", every: int = 100):
        if kind not in KINDS:
            raise ValueError(f"train.log: expected one of {list(KINDS)}, got {kind!r}")
        self.out_dir = Path(out_dir)
        self.kind = kind
        self.every = max(1, int(every))
        self._writer_class = summary_writer_class() if kind == "tensorboard" else None
        self._file = None
        self._tb = None
        self._t0 = time.perf_counter()

    @property
    def path(self) -> Path:
        return self.out_dir / LOG_FILE

    @property
    def images(self) -> int:
        """How many evaluation renders the log takes (0 without TensorBoard: evaluation keeps none)."""
        return TENSORBOARD_IMAGES if self._tb is not None else 0

    def open(self, start_step: int = 0) -> "TrainLog":
        if self.kind == "none":
            return self
        self.close()
        self.out_dir.mkdir(parents=True, exist_ok=True)
        _keep_until(self.path, start_step)
        self._file = open(self.path, "a", encoding="utf-8")
        if self._writer_class is not None:
            # purge_step hides events a previous run logged past the checkpoint this one resumes from.
            self._tb = self._writer_class(log_dir=str(self.out_dir / TENSORBOARD_DIR),
                                          purge_step=start_step + 1 if start_step else None)
        self._t0 = time.perf_counter()
        return self

    def __enter__(self) -> "TrainLog":
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        if self._tb is not None:
            self._tb.close()
            self._tb = None

    def due(self, step: int, total: int) -> bool:
        return step % self.every == 0 or step >= total

    def train(self, step: int, info: dict, lrs: Dict[str, float], train_seconds: float) -> None:
        """One training step (info as Trainer.train_step returns it; lrs: {param group: learning rate})."""
        entry = {"type": "train", "step": step, "loss": info["loss"], "losses": dict(info["values"]),
                 "psnr": info.get("psnr"), "num_primitives": info["num_primitives"], "lr": dict(lrs),
                 "train_seconds": round(train_seconds, 3), "elapsed": self._elapsed()}
        self._write(entry)
        if self._tb is not None:
            scalars = {"train/loss": entry["loss"], "train/psnr": entry["psnr"],
                       "train/num_primitives": entry["num_primitives"]}
            scalars.update({f"loss/{k}": v for k, v in entry["losses"].items()})
            scalars.update({f"lr/{k}": v for k, v in entry["lr"].items()})
            self._scalars(scalars, step)

    def eval(self, step: int, metrics: dict, *, num_primitives: int, train_seconds: float,
             final: bool = False) -> None:
        """One evaluation (metrics as Evaluator.evaluate returns them; "images" go to TensorBoard)."""
        entry = {"type": "eval", "step": step, "split": metrics["split"], "psnr": metrics["psnr"],
                 "ssim": metrics["ssim"], "lpips": metrics["lpips"], "num_views": metrics["num_views"],
                 "num_primitives": num_primitives, "train_seconds": round(train_seconds, 3),
                 "elapsed": self._elapsed(), "final": final}
        self._write(entry)
        if self._tb is not None:
            self._scalars({f"eval/{k}": entry[k] for k in ("psnr", "ssim", "lpips")}, step)
            for name, rgb in metrics.get("images", {}).items():
                self._tb.add_image(f"eval/{Path(name).stem}", rgb.numpy(), step, dataformats="HWC")

    def event(self, kind: str, step: int, fields: dict, *, train_seconds: float) -> None:
        """Another kind of line (`type` kind), e.g. train.steps=auto's "validation" scores and "schedule"
        decisions; numeric fields also go to TensorBoard as kind/name."""
        entry = {"type": kind, "step": step, **fields, "train_seconds": round(train_seconds, 3),
                 "elapsed": self._elapsed()}
        self._write(entry)
        if self._tb is not None:
            self._scalars({f"{kind}/{k}": v for k, v in fields.items()
                           if isinstance(v, (int, float)) and not isinstance(v, bool)}, step)

    def _elapsed(self) -> float:
        return round(time.perf_counter() - self._t0, 3)

    def _write(self, entry: dict) -> None:
        if self._file is None:
            return
        self._file.write(json.dumps(_finite_or_none(entry), allow_nan=False) + "\n")
        self._file.flush()

    def _scalars(self, values: Dict[str, Optional[float]], step: int) -> None:
        for tag, v in values.items():
            if v is not None and math.isfinite(v):
                self._tb.add_scalar(tag, v, step)


def _finite_or_none(value):
    """NaN/Inf become null: JSON has no spelling for them."""
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _keep_until(path: Path, step: int) -> None:
    """Start the log of a run that begins at `step`: empty for a new run; for a resume, the entries up to `step`
    (later ones will be logged again; a line cut by a hard kill is dropped)."""
    kept = []
    if step and path.is_file():
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            if isinstance(entry, dict) and isinstance(entry.get("step"), int) and entry["step"] <= step:
                kept.append(line + "\n")
    atomic_write_bytes(path, "".join(kept).encode("utf-8"))
