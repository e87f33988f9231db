"""Bad input to rasterize_surfels gets a ValueError that names the argument."""
import pytest
import torch

from reference_surfels import random_surfel_scene
from warpgs import rasterize_surfels


def call(**over):
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in random_surfel_scene(n=8, seed=0).items()}
    a = dict(means=s["means"], quats=s["quats"], scales=s["scales"], opacities=s["opacities"], colors=s["colors"],
             viewmat=s["viewmat"], K=s["K"], width=s["width"], height=s["height"])
    kw = {}
    for k, v in over.items():
        (a if k in a else kw)[k] = v
    return rasterize_surfels(**a, **kw)


@pytest.mark.parametrize("name,value,match", [
    ("means", torch.zeros(8, 2), "means"),
    ("quats", torch.zeros(7, 4), "quats"),
    ("scales", torch.zeros(8, 3), r"scales: expected shape \[8, 2\]"),
    ("opacities", torch.zeros(8, 1), "opacities"),
    ("colors", torch.zeros(8, 4), "colors"),
    ("viewmat", torch.eye(3), "viewmat"),
    ("K", torch.eye(4), "K"),
    ("background", torch.zeros(4), "background"),
    ("features", torch.zeros(9, 2), "features"),
])
def test_wrong_shapes(name, value, match):
    with pytest.raises(ValueError, match=match):
        call(**{name: value})


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmat", "K"])
def test_wrong_dtypes_and_non_finite_values(name):
    s = random_surfel_scene(n=8, seed=0)
    with pytest.raises(ValueError, match=f"{name}: expected dtype float32"):
        call(**{name: s[name].clone()})
    bad = s[name].float().clone()
    bad.view(-1)[0] = float("nan")
    with pytest.raises(ValueError, match=f"{name} contains NaN or Inf"):
        call(**{name: bad})


@pytest.mark.parametrize("over,match", [
    (dict(opacities=torch.full((8,), -0.5)), "opacities must lie in"),
    (dict(width=0), "width"),
    (dict(near=2.0, far=1.0), "near"),
    (dict(sh_degree=2, colors=torch.zeros(8, 4, 3)), "needs 9 SH coefficients"),
    (dict(outputs=("rgb", "normals")), "unknown"),
    (dict(outputs=("features",)), "features"),
    (dict(scales=torch.empty(8, 2, device="meta")), "one device"),
])
def test_bad_arguments(over, match):
    with pytest.raises(ValueError, match=match):
        call(**over)


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmat", "K", "background"])
def test_pipeline_checks_name_the_argument(monkeypatch, name):
    """As GPU renders check (kernels/input_checks.py's flags, read at the pipeline's sync), here on the CPU."""
    from warpgs.render import validation
    monkeypatch.setattr(validation, "PIPELINE_CHECK_DEVICES", {"cpu", "cuda"})
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in random_surfel_scene(n=8, seed=0).items()}
    bad = torch.zeros(3) if name == "background" else s[name].clone()
    bad.view(-1)[-1] = float("inf")
    with pytest.raises(ValueError, match=f"^{name} contains NaN or Inf"):
        call(**{name: bad})
    with pytest.raises(ValueError, match="opacities must lie in"):
        call(opacities=torch.full((8,), 1.5))
    views, Ks = torch.stack([s["viewmat"], s["viewmat"]]), torch.stack([s["K"], s["K"]])
    assert torch.equal(call(viewmat=views, K=Ks).rgb, call(viewmat=views, K=Ks, check_inputs=False).rgb)
