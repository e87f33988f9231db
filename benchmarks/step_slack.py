"""Is a GPU training step bound by the GPU or by the host? Steps timed with a fixed extra GPU job queued before each
(torch.cuda._sleep of a given length), the lengths interleaved block by block on one warmed-up Trainer.

    python benchmarks/step_slack.py data/bonsai800s --warmup 3000 --sleeps-us 0,250,500,1000,2000 train.steps=30000

If the GPU is the bottleneck, every microsecond of added GPU work adds a microsecond to the step (slope 1 from the
first sleep); if the host is, the GPU has idle time to absorb it and the step does not move until the sleep exceeds
that slack. So the curve says what a change can buy before it is made: removing GPU work (e.g. a kernel made
faster) helps only a GPU-bound step, removing host work (launches, Python) only a host-bound one. The step keeps
densifying while it is timed (as in training), so the lengths are interleaved in blocks of `--steps` steps over
`--rounds` rounds and each length's block means are averaged.
Writes benchmarks/results/step_slack_<capture>_cuda[_<tag>].json ($OUT when set).
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch

from common import write_json
from profile_train_step import capture_arguments, time_steps, warmed_trainer


def sleep_cycles_per_us() -> float:
    """GPU clock cycles per microsecond of torch.cuda._sleep, measured with CUDA events."""
    torch.cuda._sleep(1_000_000)  # the first call may pay for a launch set-up
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    cycles = 20_000_000
    start.record()
    torch.cuda._sleep(cycles)
    end.record()
    end.synchronize()
    return cycles / (start.elapsed_time(end) * 1e3)


def slack_summary(curve: list) -> dict:
    """From [(sleep_us, ms_per_step)] (sleep 0 first): each sleep's added step time as a share of the sleep (1: the
    GPU was the bottleneck; 0: the sleep fitted in idle GPU time), and the largest sleep absorbed to within 10%."""
    base = curve[0][1]
    shares = [(us, (ms - base) * 1e3 / us) for us, ms in curve[1:]]
    absorbed = [us for us, share in shares if share < 0.1]
    return {"added_share": shares, "absorbed_up_to_us": max(absorbed) if absorbed else 0}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    capture_arguments(ap, 200, "steps per timed block")
    ap.add_argument("--sleeps-us", default="0,250,500,1000,2000", help="GPU sleeps before each step, microseconds")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_intermixed_args(argv)
    if not torch.cuda.is_available() or not args.device.startswith("cuda"):
        raise SystemExit("step_slack.py: needs a CUDA device (it measures the GPU's idle time in a step)")
    sleeps = [int(v) for v in args.sleeps_us.split(",")]
    if sleeps[0] != 0 or any(v <= 0 for v in sleeps[1:]):
        raise SystemExit(f"--sleeps-us: expected 0 first, then positive lengths, got {args.sleeps_us}")
    with tempfile.TemporaryDirectory() as tmp:
        trainer = warmed_trainer(args, tmp)
        per_us = sleep_cycles_per_us()
        blocks = {us: [] for us in sleeps}
        first = trainer.num_primitives
        for _ in range(args.rounds):
            for us in sleeps:
                sleep = (lambda cycles=int(us * per_us): torch.cuda._sleep(cycles)) if us else None
                blocks[us].append(1e3 * time_steps(trainer, args.steps, args.device, before_step=sleep))
        curve = [(us, sum(b) / len(b)) for us, b in blocks.items()]
    result = {"data": args.data, "warmup": args.warmup, "steps": args.steps, "rounds": args.rounds,
              "primitives": [first, trainer.num_primitives], "sleep_cycles_per_us": per_us,
              "blocks_ms": {str(us): b for us, b in blocks.items()}, "ms_per_step": dict((str(us), ms) for us, ms in curve),
              **slack_summary(curve), "gpu": torch.cuda.get_device_name()}
    print(f"{first} -> {trainer.num_primitives} primitives; ms a step by GPU sleep before it:")
    for (us, ms), (_, share) in zip(curve, [(0, None)] + result["added_share"]):
        print(f"  {us:6d} us: {ms:6.2f} ms" + ("" if share is None else f"  (+{share:.2f} of the sleep)"))
    print(f"  absorbed to within 10%: up to {result['absorbed_up_to_us']} us")
    write_json(f"step_slack_{Path(args.data).name}_cuda" + (f"_{args.tag}" if args.tag else ""), result)
    return result


if __name__ == "__main__":
    main()
