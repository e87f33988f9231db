"""benchmarks/stanford_lightfield.py: the Stanford archive's rectified views as a light-field folder (grid positions,
centres from the measured parallax, the reference plane)."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from data_fixtures import write_rgb

from warpgs.data import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import stanford_lightfield  # noqa: E402


def _stanford_folder(root: Path, rows=range(4, 8), cols=range(2, 6)) -> dict:
    """Views named as the archive names them: row, column, then the parallax (Y, X); Y falls by ~5 a row (the
    camera moves up), X grows by ~5 a column (it moves right), with some jitter."""
    rng = np.random.default_rng(0)
    parallax = {}
    for r in rows:
        for c in cols:
            jitter = rng.normal(0, 0.3, 2)
            y, x = round(-800.0 - 5.0 * r + jitter[0], 6), round(-3300.0 + 5.0 * c + jitter[1], 6)
            name = f"out_{r:02d}_{c:02d}_{y:.6f}_{x:.6f}_.png"
            write_rgb(root / name, 40, 24, seed=r * 10 + c)
            parallax[name] = (r, c, y, x)
    write_rgb(root / "thumbnail.png", 8, 8)  # not a view: left out
    return parallax


def test_views_become_a_light_field_with_measured_centres(tmp_path):
    parallax = _stanford_folder(tmp_path / "src")
    stanford_lightfield.main([str(tmp_path / "src"), str(tmp_path / "lf"), "--infinity-shift", "8"])
    spec = json.loads((tmp_path / "lf" / "lightfield.json").read_text())
    assert (spec["rows"], spec["cols"]) == (4, 4) and len(spec["views"]) == 16 and spec["reference_depth"] == 1.0
    assert spec["intrinsics"] == {"fx": 40.0, "fy": 40.0, "cx": 20.0, "cy": 12.0}
    assert spec["views"][next(n for n in parallax if n.startswith("out_04_02_"))] == [0, 0]
    centres = {n: np.array(xy) for n, xy in spec["centres"].items()}
    # The middle view (rows 4-7, cols 2-5: row 5 or 6, col 3 or 4; the first of the nearest) sits at the origin.
    origin = [n for n, xy in centres.items() if np.allclose(xy, 0.0)]
    assert len(origin) == 1 and parallax[origin[0]][:2] == (5, 3)
    # Centres follow the measured parallax, not the grid: one scale for both axes, +x right, +y down.
    ref = parallax[origin[0]]
    steps = [abs(parallax[a][3] - parallax[b][3]) for a in parallax for b in parallax
             if parallax[a][0] == parallax[b][0] and parallax[b][1] == parallax[a][1] + 1]
    scale = 8.0 / (40.0 * np.median(steps))
    for n, (r, c, y, x) in parallax.items():
        np.testing.assert_allclose(centres[n], [scale * (x - ref[3]), scale * (y - ref[2])], rtol=1e-9, atol=1e-12)
    right = [n for n in parallax if parallax[n][:2] == (5, 5)][0]
    up = [n for n in parallax if parallax[n][:2] == (7, 3)][0]
    assert centres[right][0] > 0 and centres[up][1] < 0  # a later column is right, a later row higher
    # It loads as a rectified array: the 3x3 grid spread over the 4x4 trains, the rest tests.
    scene = load_scene(tmp_path / "lf")
    assert len(scene.train) == 9 and len(scene.test) == 7
    on_plane = np.array([0.01, -0.02, 1.0])
    pixels = [cam.K @ (cam.viewmat[:3, :3] @ on_plane + cam.viewmat[:3, 3]) for cam in scene.cameras]
    np.testing.assert_allclose([p[:2] / p[2] for p in pixels], [pixels[0][:2] / pixels[0][2]] * 16, atol=1e-9)


def test_a_row_and_column_range_and_bad_input(tmp_path):
    _stanford_folder(tmp_path / "src")
    stanford_lightfield.main([str(tmp_path / "src"), str(tmp_path / "lf"), "--rows", "5-7", "--cols", "3-5"])
    spec = json.loads((tmp_path / "lf" / "lightfield.json").read_text())
    assert (spec["rows"], spec["cols"]) == (3, 3) and sorted(spec["views"].values())[0] == [0, 0]
    assert len(list((tmp_path / "lf" / "images").iterdir())) == 9
    with pytest.raises(SystemExit, match="no views named"):
        stanford_lightfield.main([str(tmp_path / "src"), str(tmp_path / "none"), "--rows", "20-21"])
    with pytest.raises(SystemExit, match="expected a range"):
        stanford_lightfield.main([str(tmp_path / "src"), str(tmp_path / "x"), "--rows", "a-b"])
    with pytest.raises(SystemExit, match="not a folder"):
        stanford_lightfield.main([str(tmp_path / "missing"), str(tmp_path / "x")])
