"""`warpgs-render --outputs rgb,depth,normal,alpha` (issue 32 item 3): the depth writers read back what they wrote
(16-bit PNG to its quantum, EXR exactly), the files hold what the render op gives, normals come from surfels only
(3D Gaussians get a clear error), and the previews colour what is valid and leave the rest black."""
import numpy as np
import pytest
import torch

from train_fixtures import quick_overrides
from warpgs.cli.commands import load_run, render_main
from warpgs.data.depth.files import read_depth, read_depth_file, read_exr_channels, write_depth_png16, write_exr
from warpgs.data.formats.image_io import read_image
from warpgs.model.maps import depth_colours, normal_colours, parse_maps, render_outputs, stretch_range


def test_depth_png16_round_trip_to_its_quantum(tmp_path):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.05, 60.0, (7, 9))
    valid = rng.random((7, 9)) > 0.2
    depth[0, 0] = 70.0  # beyond 65535 / 1000
    valid[0, 0] = True
    beyond = write_depth_png16(tmp_path / "d.png", depth, 1000.0, valid)
    assert beyond == 1
    got, ok = read_depth(tmp_path / "d.png", "depth", scale=1 / 1000)
    assert np.array_equal(ok, valid & (depth <= 65.535))
    assert np.abs(got[ok] - depth[ok]).max() <= 0.5 / 1000 + 1e-6
    assert (got[~ok] == 0).all()
    # A valid depth under half a level stays a depth (the nearest the format holds), not "no depth".
    write_depth_png16(tmp_path / "near.png", np.array([[0.0002, 0.0, 2.0]]), 1000.0, np.array([[True, False, True]]))
    got, ok = read_depth(tmp_path / "near.png", "depth", scale=1 / 1000)
    assert ok.tolist() == [[True, False, True]] and got[0, 0] == pytest.approx(0.001) and got[0, 2] == pytest.approx(2.0)
    for bad in (0.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="e.png: depth scale must be positive and finite"):
            write_depth_png16(tmp_path / "e.png", depth, bad)


def test_depth_and_normal_exr_round_trip_exactly(tmp_path):
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.1, 1e4, (5, 6)).astype(np.float32)
    valid = rng.random((5, 6)) > 0.3
    write_exr(tmp_path / "d.exr", np.where(valid, depth, 0), "depth", valid=valid)
    got, ok, kind = read_depth_file(tmp_path / "d.exr")
    assert kind == "depth" and np.array_equal(ok, valid) and np.array_equal(got[ok], depth[valid])
    via_inverse, ok2 = read_depth(tmp_path / "d.exr")  # the loaders' path, through 1 / depth and back
    assert np.array_equal(ok2, valid) and np.allclose(via_inverse[ok], depth[valid], rtol=1e-6)
    from warpgs.data.depth.files import write_exr_channels

    n = rng.normal(size=(5, 6, 3)).astype(np.float32)
    write_exr_channels(tmp_path / "n.exr", {"normal": n})
    assert np.array_equal(read_exr_channels(tmp_path / "n.exr")["normal"], n)


def test_previews_colour_valid_pixels_only():
    depth = torch.tensor([[1.0, 2.0], [4.0, 8.0]])
    valid = torch.tensor([[True, True], [True, False]])
    c = depth_colours(depth, valid)
    assert c.shape == (2, 2, 3) and (c[1, 1] == 0).all() and (c[valid] > 0).any(dim=-1).all()
    assert c[0, 0].sum() > c[1, 0].sum()  # near is light, far is dark
    normal = torch.tensor([[[0.0, 0.0, 2.0], [0.0, -1.0, 0.0]]])
    nc = normal_colours(normal, torch.tensor([[True, False]]))
    assert torch.allclose(nc[0, 0], torch.tensor([0.5, 0.5, 1.0])) and (nc[0, 1] == 0).all()


def test_preview_stretch_takes_more_than_torch_quantiles_limit():
    # More values than torch.quantile takes (2^24), as in the depth preview of a 6000x4000 photo.
    inv = torch.linspace(1.0, 2.0, 2**24 + 7)
    lo, hi = stretch_range(inv)
    assert abs(lo - 1.02) < 1e-3 and abs(hi - 1.98) < 1e-3


def test_output_names_and_kinds_are_checked():
    assert parse_maps("rgb, depth,depth") == ("rgb", "depth")
    with pytest.raises(ValueError, match="--outputs: expected a comma-separated list"):
        parse_maps("rgb,height")
    assert render_outputs("surfels", ["depth", "normal"]) == ("median_depth", "normal", "alpha")
    assert render_outputs("gaussians", ["rgb", "depth"]) == ("rgb", "depth", "alpha")
    with pytest.raises(ValueError, match=r"model.kind=gaussians cannot render \['normal'\] \(model.kind=surfels can"):
        render_outputs("gaussians", ["normal"])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    from warpgs.train.trainer import Trainer

    out = {}
    for kind in ("gaussians", "surfels"):
        out[kind] = tmp_path_factory.mktemp(kind)
        Trainer(None, overrides=quick_overrides(out[kind], steps=2, **{"model.kind": kind}), quiet=True).fit()
    return out


def _direct(run, outputs):
    """The first test view rendered through the run's own Trainer."""
    trainer = load_run(run)
    _, views = trainer.eval_views("test")
    with torch.no_grad():
        return views[0], trainer.render(views[0], outputs)


@pytest.mark.parametrize("kind", ["gaussians", "surfels"])
def test_render_cli_writes_the_maps_of_the_render(runs, kind, tmp_path, capsys):
    maps = "rgb,depth,alpha" + (",normal" if kind == "surfels" else "")
    assert render_main(["--model", str(runs[kind]), "--outputs", maps, "--out", str(tmp_path)]) == 0
    assert "files) of" in capsys.readouterr().out
    view, r = _direct(runs[kind], render_outputs(kind, parse_maps(maps)))
    stem = view.name.rsplit(".", 1)[0].split("/")[-1]
    alpha = r.alpha[..., 0].numpy()
    valid = alpha >= 0.5
    assert valid.any()
    depth = (r.median_depth if kind == "surfels" else r.depth)[..., 0].numpy()
    got, ok, _ = read_depth_file(tmp_path / f"{stem}_depth.exr")
    assert np.array_equal(ok, valid & (depth > 0)) and np.array_equal(got[ok], depth[ok])
    png, png_ok = read_depth(tmp_path / f"{stem}_depth.png", "depth", scale=1 / 1000)
    assert np.array_equal(png_ok, ok) and np.abs(png[ok] - depth[ok]).max() <= 0.5 / 1000 + 1e-6
    preview, _ = read_image(tmp_path / f"{stem}_depth_preview.png")
    assert (preview[~ok] == 0).all() and (preview[ok].max(axis=-1) > 0).all()
    a, _ = read_image(tmp_path / f"{stem}_alpha.png")
    assert np.abs(a[..., 0] - alpha).max() <= 0.5 / 255 + 1e-6
    assert (tmp_path / f"{stem}.png").is_file()
    if kind == "surfels":
        n = read_exr_channels(tmp_path / f"{stem}_normal.exr")["normal"]
        assert np.allclose(np.linalg.norm(n[valid], axis=-1), 1.0, atol=1e-5) and (n[~valid] == 0).all()
        want = r.normal.numpy()[valid]
        assert np.allclose(n[valid], want / np.linalg.norm(want, axis=-1, keepdims=True), atol=1e-6)
        rgb, _ = read_image(tmp_path / f"{stem}_normal.png")
        assert np.abs(rgb[valid] - (n[valid] + 1) / 2).max() <= 0.5 / 255 + 1e-6


def test_normals_of_gaussians_are_a_clear_error(runs, tmp_path, capsys):
    assert render_main(["--model", str(runs["gaussians"]), "--outputs", "rgb,normal", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "warpgs-render: error: --outputs: model.kind=gaussians cannot render ['normal']" in err
    assert not any(tmp_path.iterdir())
    for bad in ("0", "inf"):
        assert render_main(["--model", str(runs["gaussians"]), "--outputs", "depth", "--depth-scale", bad]) == 2
        assert "--depth-scale: expected a positive number" in capsys.readouterr().err
