"""benchmarks/raster_pool.py: raster.py's per-process ratios pool into a mean and its standard error."""
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import raster_pool  # noqa: E402


def _row(n, fwd, fwd_bwd):
    return {"primitive": "gaussians", "n": n, "resolution": "1920x1080", "fwd_ms": fwd, "fwd_bwd_ms": fwd_bwd,
            "gsplat_fwd_ms": 1.0, "gsplat_fwd_bwd_ms": 2.0, "ratio_fwd": fwd, "ratio_fwd_bwd": fwd_bwd / 2.0}


def test_processes_from_files_and_collections_pool_by_size(tmp_path):
    (tmp_path / "a.json").write_text(json.dumps({"meta": {}, "rows": [_row(100, 0.9, 2.0), _row(1000, 1.0, 2.0)]}))
    (tmp_path / "b.json").write_text(json.dumps({"runs": {
        "new_1": {"meta": {}, "rows": [_row(100, 1.1, 2.2)]},
        "old_1": {"meta": {}, "rows": [_row(100, 9.0, 9.0)]},  # another code version: not picked
        "new_2": {"meta": {}, "rows": [_row(100, 1.0, 1.8), {"primitive": "gaussians", "n": 100,
                                                             "resolution": "1920x1080", "ratio_fwd": None}]}}}))
    rows = raster_pool.pool([str(tmp_path / "a.json"), f"{tmp_path / 'b.json'}:new_"])
    by_n = {r["n"]: r for r in rows}
    assert by_n[100]["processes"] == 3 and by_n[1000]["processes"] == 1
    assert by_n[100]["ratio_fwd_mean"] == pytest.approx(1.0)
    assert by_n[100]["ratio_fwd_se"] == pytest.approx(0.1 / 3 ** 0.5)  # sd 0.1 over three processes
    assert by_n[100]["ratio_fwd_bwd_mean"] == pytest.approx(1.0)


def test_a_collection_without_the_prefix_is_named_in_the_error(tmp_path):
    (tmp_path / "c.json").write_text(json.dumps({"runs": {"old_1": {"rows": []}}}))
    with pytest.raises(SystemExit, match="c.json: no run whose name starts with 'new_'"):
        raster_pool.pool([f"{tmp_path / 'c.json'}:new_"])
