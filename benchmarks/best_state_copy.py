"""What a train.steps=auto run pays at each new best validation score: copying the model with its Adam moments to
host memory (train/best_state.py). The 3DGS parameter layout (59 floats a primitive: means 3, quats 4, scales 3,
opacity 1, SH 48) times three (value, exp_avg, exp_avg_sq), copied as before (fresh pageable memory, the host waits
for each tensor) and as now (train/host_copies.py: reused page-locked buffers, enqueued without a host sync, the
time until they have landed), and a device-side clone for scale.

    python benchmarks/best_state_copy.py --device cuda --primitives 1000000

Writes benchmarks/results/best_state_copy_<device>[_<tag>].json.
"""
from __future__ import annotations

import argparse
import sys

import torch

from common import ROOT, run_host, time_call, write_json

sys.path.insert(0, str(ROOT))

from warpgs.train.host_copies import HostCopies  # noqa: E402

COLUMNS = {"means": (3,), "quats": (4,), "scales": (3,), "opacities": (), "sh0": (1, 3), "shN": (15, 3)}


def model_tensors(n: int, device: str) -> dict:
    """{(name, part): tensor} of n primitives: each parameter and its two Adam moments."""
    g = torch.Generator(device=device).manual_seed(0)
    return {(name, part): torch.randn((n, *shape), generator=g, device=device)
            for name, shape in COLUMNS.items() for part in ("value", "exp_avg", "exp_avg_sq")}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--primitives", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    tensors = model_tensors(args.primitives, args.device)
    nbytes = sum(t.numel() * t.element_size() for t in tensors.values())
    host = HostCopies()

    def into_host_buffers():
        for key, t in tensors.items():
            host.copy(key, t)
        host.wait()

    ms = {"pageable_copy": time_call(lambda: [t.to("cpu", copy=True) for t in tensors.values()], args.device,
                                     repeats=args.repeats),
          "host_copies": time_call(into_host_buffers, args.device, repeats=args.repeats),
          "device_clone": time_call(lambda: [t.clone() for t in tensors.values()], args.device, repeats=args.repeats)}
    for k, v in ms.items():
        print(f"{k:>14}: {v:9.3f} ms  ({nbytes / v / 1e6:.1f} GB/s)")
    name = f"best_state_copy_{args.device.split(':')[0]}" + (f"_{args.tag}" if args.tag else "")
    path = write_json(name, {"device": args.device, "primitives": args.primitives, "bytes": nbytes, "median_ms": ms,
                             "host": run_host(args.device), "command": " ".join(sys.argv)})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
