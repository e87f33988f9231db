"""benchmarks/step_time_ab.py: two code versions' training steps timed in alternating processes."""
import json
import sys
from pathlib import Path

import pytest

from train_fixtures import small_orbit

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import step_time_ab  # noqa: E402


def test_two_versions_are_timed_in_alternating_processes(tmp_path, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path))
    result = step_time_ab.main([str(small_orbit()), "--trees", f"a={ROOT},b={ROOT}@train.fused_ssim=true", "--device", "cpu",
                                "--warmup", "2", "--steps", "2", "--blocks", "2", "--rounds", "2", "--tag", "t",
                                "strategy.refine_start=1000"])
    assert [(r["version"], r["round"]) for r in result["runs"]] == [("a", 1), ("b", 1), ("a", 2), ("b", 2)]
    assert [r["overrides"] for r in result["runs"][:2]] == [[], ["train.fused_ssim=true"]]
    assert all(len(r["ms"]) == 2 and min(r["ms"]) > 0 for r in result["runs"])
    assert result["ratio_to_first"]["a"] == 1.0 and result["ratio_to_first"]["b"] > 0
    saved = json.loads((tmp_path / "step_time_ab_orbit64_cpu_t.json").read_text())
    assert saved["ms_per_step"] == result["ms_per_step"]


def test_trees_must_be_named_folders_holding_warpgs(tmp_path):
    with pytest.raises(SystemExit, match="NAME=PATH"):
        step_time_ab.parse_trees(f"{ROOT}")
    with pytest.raises(SystemExit, match="holds no warpgs"):
        step_time_ab.parse_trees(f"a={ROOT},b={tmp_path}")
    with pytest.raises(SystemExit, match="at least two"):
        step_time_ab.parse_trees(f"a={ROOT}")
    with pytest.raises(SystemExit, match="key=value"):
        step_time_ab.parse_trees(f"a={ROOT},b={ROOT}@fused")
    assert step_time_ab.parse_trees(f"a={ROOT},b={ROOT}@x=1;y=2")["b"] == (str(ROOT), ["x=1", "y=2"])


def test_a_tree_brings_its_own_kernels_past_an_editable_install(tmp_path):
    """The tree's kernels/ must be the warpgs.kernels a worker imports, not the installed checkout's."""
    import shutil
    import subprocess

    tree = tmp_path / "tree"
    shutil.copytree(ROOT / "warpgs", tree / "warpgs", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "kernels", tree / "kernels", ignore=shutil.ignore_patterns("__pycache__"))
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import step_time_ab; step_time_ab.import_tree(sys.argv[2]); "
            "import warpgs.kernels.blend as b; print(b.__file__)")
    out = subprocess.run([sys.executable, "-c", code, str(ROOT / "benchmarks"), str(tree)], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert Path(out.stdout.strip().splitlines()[-1]).resolve() == (tree / "kernels" / "blend.py").resolve()
