"""The wheel carries what an installed warpgs needs beyond the Python package: the Warp kernels (kernels/ as
warpgs.kernels) and the YAML presets (configs/ as warpgs/configs), so `warpgs-train <preset>` works from it."""
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def wheel_names(tmp_path_factory):
    # Built from a copy (pip builds in place and would leave build/ and *.egg-info in the checkout), the way
    # `pip install .` builds it: isolated, with the backend pyproject.toml names.
    src, out = tmp_path_factory.mktemp("src"), tmp_path_factory.mktemp("wheel")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    for name in ("warpgs", "kernels", "configs"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(src)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (wheel,) = out.glob("warpgs-*.whl")
    with zipfile.ZipFile(wheel) as z:
        return set(z.namelist())


def test_wheel_ships_every_preset(wheel_names):
    presets = sorted(p.name for p in (ROOT / "configs").glob("*.yaml"))
    assert presets, "no presets in configs/"
    missing = [name for name in presets if f"warpgs/configs/{name}" not in wheel_names]
    assert not missing, missing


def test_wheel_ships_the_kernels(wheel_names):
    kernels = sorted(p.name for p in (ROOT / "kernels").glob("*.py"))
    missing = [name for name in kernels if f"warpgs/kernels/{name}" not in wheel_names]
    assert not missing, missing
