"""Bad input gets a ValueError that names the argument."""
import pytest
import torch

from random_scenes import random_scene
from warpgs import rasterize


def args(**over):
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in random_scene(n=8, seed=0).items()}
    a = dict(means=s["means"], quats=s["quats"], scales=s["scales"], opacities=s["opacities"], colors=s["colors"],
             viewmat=s["viewmat"], K=s["K"], width=s["width"], height=s["height"])
    kw = {}
    for k, v in over.items():
        (a if k in a else kw)[k] = v
    return a, kw


def call(**over):
    a, kw = args(**over)
    return rasterize(**a, **kw)


@pytest.mark.parametrize("name,value,match", [
    ("means", torch.zeros(8, 2), "means"),
    ("quats", torch.zeros(7, 4), "quats"),
    ("scales", torch.zeros(8, 2), "scales"),
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


def test_a_batch_of_no_cameras_is_named():
    with pytest.raises(ValueError, match="viewmat: a batch of 0 cameras"):
        call(viewmat=torch.zeros(0, 4, 4), K=torch.zeros(0, 3, 3))


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmat", "K"])
def test_wrong_dtypes(name):
    a, _ = args()
    with pytest.raises(ValueError, match=f"{name}: expected dtype float32"):
        call(**{name: a[name].double()})


@pytest.mark.parametrize("name", ["means", "quats", "scales", "colors", "viewmat", "K"])
def test_non_finite_values(name):
    a, _ = args()
    bad = a[name].clone()
    bad.view(-1)[0] = float("nan")
    with pytest.raises(ValueError, match=f"{name} contains NaN or Inf"):
        call(**{name: bad})
    bad.view(-1)[0] = float("inf")
    with pytest.raises(ValueError, match=f"{name} contains NaN or Inf"):
        call(**{name: bad})


def test_opacities_outside_unit_interval():
    with pytest.raises(ValueError, match="opacities must lie in"):
        call(opacities=torch.full((8,), 1.5))


def test_mixed_devices():
    a, _ = args()
    with pytest.raises(ValueError, match="one device"):
        call(scales=torch.empty(8, 3, device="meta"))


@pytest.mark.parametrize("over,match", [
    (dict(width=0), "width"),
    (dict(height=2.5), "height"),
    (dict(near=0.0), "near"),
    (dict(near=2.0, far=1.0), "near"),
    (dict(sh_degree=4, colors=torch.zeros(8, 16, 3)), "sh_degree"),
    (dict(sh_degree=2, colors=torch.zeros(8, 4, 3)), "needs 9 SH coefficients"),
    (dict(outputs=("rgb", "normals")), "unknown"),
    (dict(outputs=("features",)), "features"),
    (dict(alpha_max=1.0), "alpha_max"),
    (dict(alpha_max=0.5, alpha_min=0.6), "alpha_min"),
])
def test_bad_arguments(over, match):
    with pytest.raises(ValueError, match=match):
        call(**over)


def test_not_a_tensor():
    with pytest.raises(ValueError, match="means: expected a torch.Tensor"):
        call(means=[[0.0, 0.0, 1.0]] * 8)


def test_transposed_inputs_that_need_gradients_work():
    """A transposed (non-contiguous) leaf still renders and gets its gradient (the grad buffer is contiguous)."""
    import torch

    from random_scenes import random_scene
    from warpgs import rasterize

    s = random_scene(n=20, seed=0, num_features=3)
    feats = s["features"].float().t().contiguous().t().detach().requires_grad_(True)  # plain [N, 3]
    feats_t = s["features"].float().t().detach().requires_grad_(True)  # [3, N]; .t() gives a strided [N, 3]
    outs = []
    for leaf, f in ((feats, feats), (feats_t, feats_t.t())):
        out = rasterize(*(s[k].float() for k in ("means", "quats", "scales", "opacities", "colors", "viewmat", "K")),
                        s["width"], s["height"], features=f, outputs=("features",))
        out.features.sum().backward()
        outs.append(leaf.grad.t() if leaf is feats_t else leaf.grad)
    assert torch.allclose(outs[0], outs[1]) and outs[0].abs().sum() > 0


@pytest.fixture
def checks_in_pipeline(monkeypatch):
    """Runs the finite-value checks as GPU renders do (kernels/input_checks.py's flags, read at the pipeline's
    tile-pair sync), here on the CPU."""
    from warpgs.render import validation
    monkeypatch.setattr(validation, "PIPELINE_CHECK_DEVICES", {"cpu", "cuda"})


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmat", "K", "background",
                                  "features"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_pipeline_checks_name_the_argument(checks_in_pipeline, name, bad):
    s = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in random_scene(n=8, seed=0).items()}
    over = {"background": torch.zeros(3), "features": torch.ones(8, 2)}
    value = over[name].clone() if name in over else s[name].clone()
    value.view(-1)[-1] = bad  # the last entry: the kernel must look at every row and every entry
    kw = dict(over, outputs=("rgb",))  # features given but not rendered are still checked, as before
    kw[name] = value
    with pytest.raises(ValueError, match=f"^{name} contains NaN or Inf"):
        call(**kw)


def test_pipeline_checks_unused_entries_of_K_and_range(checks_in_pipeline):
    a, _ = args()
    K = a["K"].clone()
    K[2, 0] = float("nan")  # not one of (fx, fy, cx, cy): still named, as the torch checks did
    with pytest.raises(ValueError, match="^K contains NaN or Inf"):
        call(K=K)
    with pytest.raises(ValueError, match="opacities must lie in"):
        call(opacities=torch.full((8,), 1.5))
    with pytest.raises(ValueError, match="opacities must lie in"):
        call(opacities=torch.full((8,), -0.5))


def test_pipeline_checks_batch_and_good_input(checks_in_pipeline):
    """A batch names a bad camera of any index; good input renders the same images with the checks on or off."""
    a, _ = args()
    views = torch.stack([a["viewmat"], a["viewmat"]])
    Ks = torch.stack([a["K"], a["K"]])
    Ks[1, 0, 2] = float("inf")
    with pytest.raises(ValueError, match="^K contains NaN or Inf"):
        call(viewmat=views, K=Ks)
    Ks[1, 0, 2] = a["K"][0, 2]
    checked = call(viewmat=views, K=Ks)
    unchecked = call(viewmat=views, K=Ks, check_inputs=False)
    assert torch.equal(checked.rgb, unchecked.rgb) and checked.rgb.abs().sum() > 0
