"""Renderer variants to time side by side in one process (benchmarks/raster.py, profile_stages.py).

A variant is `default` (whatever the WARPGS_* variables select) or `fast`, then optional options joined by '+':
`fast+bwd=block`, `fast+sbwd=scatter`, `fast+det=on`, `fast+keys=full`, `fast+psort=exact`. Keys: bwd (the 3D GPU
adjoint: scatter, warp_sums, block), sbwd (the surfel GPU adjoint: warp_sums, scatter, block), det (the deterministic
adjoint: on, off; a no-op for the CPU's per-thread kernels, deterministic anyway), keys (the GPU tile-key emission's
search: table, full), padj (the 3D projection's adjoint: written, generated), psort (the GPU pair sort: ahead,
padded, exact); see warpgs/render/defaults.py.
"""
from __future__ import annotations

from contextlib import contextmanager

from warpgs.render.defaults import current_raster_options, raster_options

KEYS = {"bwd": "backward_kernel", "sbwd": "surfel_backward_kernel", "det": "deterministic", "keys": "pair_search",
        "padj": "project_adjoint", "psort": "pair_sort"}
SWITCHES = {"on": True, "off": False}  # the values of on/off keys


def parse(spec: str) -> dict:
    parts = [p for p in spec.strip().split("+") if p]
    if not parts:
        raise SystemExit("empty variant")
    options = {}
    if parts[0] not in ("default", "fast"):
        raise SystemExit(f"variant {spec!r}: starts with 'default' or 'fast' (the legacy path is gone)")
    for part in parts[1:]:
        key, _, value = part.partition("=")
        if key not in KEYS or not value:
            raise SystemExit(f"variant {spec!r}: expected key=value with key in {sorted(KEYS)}")
        if KEYS[key] == "deterministic":
            if value not in SWITCHES:
                raise SystemExit(f"variant {spec!r}: det takes on or off, got {value!r}")
            value = SWITCHES[value]
        options[KEYS[key]] = value
    return options


@contextmanager
def variant(spec: str):
    """Renders inside use the variant's options; yields the options in force."""
    with raster_options(**parse(spec)) as opts:
        yield opts


def describe() -> str:
    o = current_raster_options()
    return (f"fast+bwd={o.backward_kernel}+sbwd={o.surfel_backward_kernel}+keys={o.pair_search}"
            f"+padj={o.project_adjoint}+psort={o.pair_sort}"
            + ("+det=on" if o.deterministic else ""))
