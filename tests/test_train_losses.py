"""The Python API around the trainer: custom losses (rendered outputs = the union the active terms declare),
extensions (extra per-primitive features, extra modules with their own optimizer), what the batch carries."""
import math
import subprocess
import sys

import pytest
import torch
from torch import nn

import warpgs
import warpgs.model.rendering as model_render
from train_fixtures import quick_overrides
from warpgs.train.extensions import Extension
from warpgs.losses import unregister_loss
from warpgs.train.trainer import Trainer

STEPS = 25
RENDERS = STEPS + 1  # a training render a step, and the one before the clock that compiles them (train/warm_up.py)


@pytest.fixture
def spy(monkeypatch):
    """Records the outputs of every differentiable rasterizer call (training renders; evaluation runs no_grad)."""
    calls = {"train": [], "eval": []}
    real = model_render.rasterize

    def wrapped(*args, **kwargs):
        calls["train" if torch.is_grad_enabled() else "eval"].append(tuple(kwargs["outputs"]))
        return real(*args, **kwargs)

    monkeypatch.setattr(model_render, "rasterize", wrapped)
    return calls


def _final_params(trainer):
    return torch.cat([p.detach().flatten() for p in trainer.model.params.values()])


def test_custom_loss_changes_result_and_adds_only_its_outputs(tmp_path, spy):
    base = Trainer(None, overrides=quick_overrides(tmp_path / "base", STEPS), quiet=True)
    base.fit()
    assert set(spy["train"]) == {("rgb",)} and len(spy["train"]) == RENDERS
    assert set(spy["eval"]) == {("rgb",)}
    spy["train"].clear()

    @warpgs.register_loss("_test_far", outputs=("depth",), weight=0.05)
    def far(render_out, batch, model):  # the 3-argument form is accepted too
        return -render_out.depth.mean() / 10.0

    try:
        custom = Trainer(None, overrides=quick_overrides(tmp_path / "custom", STEPS, **{"losses._test_far": None}),
                         quiet=True)
        assert [t.name for t in custom.terms] == ["l1", "dssim", "_test_far"]
        assert custom.outputs == ("rgb", "depth")
        custom.fit()
    finally:
        unregister_loss("_test_far")
    assert set(spy["train"]) == {("rgb", "depth")} and len(spy["train"]) == RENDERS
    assert not torch.equal(_final_params(base), _final_params(custom))


def test_renderer_knobs_reach_every_render(tmp_path, monkeypatch):
    seen = []
    real = model_render.rasterize

    def wrapped(*args, **kwargs):
        seen.append((kwargs["alpha_min"], kwargs["transmittance_min"], kwargs["max_sigmas"], kwargs["tile_size"]))
        return real(*args, **kwargs)

    monkeypatch.setattr(model_render, "rasterize", wrapped)
    knobs = {"train.alpha_min": 0.02, "train.transmittance_min": 0.001, "train.max_sigmas": 2.5, "train.tile_size": 4}
    Trainer(None, overrides=quick_overrides(tmp_path, 5, **knobs), quiet=True).fit()
    assert seen and set(seen) == {(0.02, 0.001, 2.5, 4)}


def test_weight_zero_removes_term_and_its_outputs(tmp_path, spy):
    @warpgs.register_loss("_test_alpha", outputs=("alpha", "inv_depth"))
    def alpha_term(render_out, batch, model, step):
        raise AssertionError("a term with weight 0 must not run")

    try:
        trainer = Trainer(None, overrides=quick_overrides(tmp_path, 3, **{"losses._test_alpha": 0}), quiet=True)
        assert trainer.outputs == ("rgb",)
        trainer.fit()
    finally:
        unregister_loss("_test_alpha")
    assert set(spy["train"]) == {("rgb",)}


def test_loss_needing_output_the_kind_cannot_render(tmp_path):
    @warpgs.register_loss("_test_normal", outputs=("normal",))
    def normal_term(render_out, batch, model, step):
        return render_out.normal.mean()

    try:
        with pytest.raises(ValueError, match=r"model.kind=gaussians cannot render \['normal'\] \(model.kind=surfels"):
            Trainer(None, overrides=quick_overrides(tmp_path, 3, **{"losses._test_normal": 1.0}), quiet=True)
    finally:
        unregister_loss("_test_normal")


def test_batch_carries_depth_priors_and_masks(tmp_path):
    seen = []

    @warpgs.register_loss("_test_prior", outputs=("inv_depth",), weight=0.1)
    def prior(render_out, batch, model, step):
        seen.append(sorted(k for k in ("inv_depth_prior", "inv_depth_valid", "depth") if k in batch))
        valid = batch["inv_depth_valid"].float()
        return ((render_out.inv_depth - batch["inv_depth_prior"]).abs() * valid).sum() / valid.sum().clamp_min(1)

    try:
        # The synthetic scene's exact depth maps stand in for priors (depth/ is a folder of depth EXRs).
        overrides = quick_overrides(tmp_path, 3, **{"losses._test_prior": None, "data.depth_priors": "depth"})
        Trainer(None, overrides=overrides, quiet=True).fit()
    finally:
        unregister_loss("_test_prior")
    assert seen == [["depth", "inv_depth_prior", "inv_depth_valid"]] * (3 + 1)  # and the warm-up's call


class _Latent(Extension):
    """A 3-channel per-primitive latent rendered through `features`, decoded by a small module."""

    def setup(self, trainer):
        n = trainer.model.num_primitives
        trainer.add_extra("latent", torch.full((n, 3), 0.1), lr=1e-2)
        trainer.add_module("decoder", nn.Linear(3, 3), lr=1e-2)


def test_extension_features_and_module_train_and_resume(tmp_path):
    @warpgs.register_loss("_test_latent", outputs=("features",), weight=0.1)
    def latent(render_out, batch, model, step):
        feats = render_out.features[..., batch["feature_slices"]["latent"]]
        return (batch["modules"]["decoder"](feats) - batch["image"]).abs().mean()

    try:
        overrides = quick_overrides(tmp_path, 20, **{"losses._test_latent": None, "train.checkpoint_every": 10})
        trainer = Trainer(None, overrides=overrides, extensions=[_Latent()], quiet=True)
        assert trainer.outputs == ("rgb", "features")
        w0 = trainer.modules["decoder"].weight.detach().clone()
        trainer.fit()
        assert not torch.equal(trainer.modules["decoder"].weight, w0)
        assert trainer.model.params["latent"].shape == (trainer.model.num_primitives, 3)
        assert not torch.allclose(trainer.model.params["latent"], torch.tensor(0.1))
        resumed = Trainer(None, overrides=overrides + ["train.steps=25"], extensions=[_Latent()], resume=True,
                          quiet=True)
        assert torch.equal(resumed.modules["decoder"].weight, trainer.modules["decoder"].weight)
        assert resumed.fit().steps == 25
    finally:
        unregister_loss("_test_latent")


def test_package_exports_are_lazy():
    code = ("import sys, warpgs, warpgs.losses, warpgs.config.loader; assert 'warp' not in sys.modules; "
            "from warpgs import register_loss, load_config; assert 'warp' not in sys.modules; "
            "from warpgs import Trainer, rasterize; assert 'warp' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
    from warpgs.losses import register_loss

    assert warpgs.register_loss is register_loss


def test_environment_background_trains_and_is_restored(tmp_path):
    overrides = quick_overrides(tmp_path, 15, **{"extensions.environment.degree": 2})
    trainer = Trainer(None, overrides=overrides, quiet=True)
    assert trainer.outputs == ("rgb", "alpha") and torch.equal(trainer.background, torch.zeros(3))
    c0 = trainer.modules["environment"].coeffs.detach().clone()
    trainer.fit()
    assert not torch.equal(trainer.modules["environment"].coeffs, c0)
    view = trainer.eval_views()[1][0]
    with torch.no_grad():
        plain = model_render.render_model(trainer.model, view.viewmat, view.K, view.width, view.height,
                                          outputs=("rgb", "alpha"))
        composite = trainer.render(view).rgb
        restored = Trainer(None, overrides=overrides, resume=True, quiet=True).render(view).rgb
    assert torch.equal(restored, composite)
    uncovered = plain.alpha[..., 0] < 0.5
    assert uncovered.any() and (composite - plain.rgb)[uncovered].abs().mean() > 0.05


def test_depth_to_normal_of_a_tilted_plane():
    from warpgs.losses.surfel_geometry import depth_to_normal

    H, W, f = 24, 32, 30.0
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    n_true = torch.tensor([0.0, 0.6, -0.8])  # camera frame, facing the camera (z < 0)
    v = torch.arange(H) + 0.5
    u = torch.arange(W) + 0.5
    rays = torch.stack([((u[None, :] - W / 2) / f).expand(H, W), ((v[:, None] - H / 2) / f).expand(H, W),
                        torch.ones(H, W)], -1)
    depth = (-3.0 / (rays @ n_true))[..., None]  # plane n . p = -3 (3 units in front)
    R = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(1)))[0]
    R = R * torch.sign(torch.det(R))
    view = torch.eye(4)
    view[:3, :3] = R
    got = depth_to_normal(depth, K, view)[1:-1, 1:-1]
    assert torch.allclose(got, (R.T @ n_true).expand_as(got), atol=1e-4)


def test_surfel_geometry_losses_run(tmp_path):
    from warpgs.cli.commands import configs_dir

    overrides = quick_overrides(tmp_path, 6, **{"losses.normal_consistency.schedule": None,
                                                "losses.distortion.weight": 10.0, "losses.distortion.schedule": None})
    trainer = Trainer(configs_dir() / "surfels.yaml", overrides=overrides, quiet=True)
    assert trainer.outputs == ("rgb", "alpha", "depth", "normal", "distortion")
    seen = []
    trainer.extensions.append(type("Spy", (Extension,), {"after_step": lambda s, t, st, info: seen.append(info)})())
    trainer.fit()
    assert set(seen[-1]["values"]) == {"l1", "dssim", "normal_consistency", "distortion"}
    assert all(math.isfinite(v) for info in seen for v in info["values"].values())


def test_environment_directions_are_kept_per_camera_tensor_and_redone_when_it_changes(monkeypatch):
    from types import SimpleNamespace

    from warpgs.model import environment

    made = []
    real = environment.ray_directions
    monkeypatch.setattr(environment, "ray_directions", lambda *a: made.append(1) or real(*a))
    ext = environment.Environment(degree=1)
    trainer = SimpleNamespace(modules={"environment": environment.EnvironmentMap(1)})
    viewmat, K = torch.eye(4), torch.tensor([[8.0, 0, 4], [0, 8.0, 3], [0, 0, 1]])
    batch = {"viewmat": viewmat, "K": K, "width": 8, "height": 6}

    def composite():
        out = SimpleNamespace(rgb=torch.zeros(6, 8, 3), alpha=torch.zeros(6, 8, 1))
        return ext.after_render(trainer, out, batch, 0).rgb

    first = composite()
    assert torch.equal(composite(), first) and len(made) == 1  # the same tensors: no second computation
    viewmat[0, 3] = 1.0  # moved in place (a translation: same directions, but the entry must be redone)
    composite()
    assert len(made) == 2
    batch["viewmat"] = viewmat.clone()  # a new tensor of equal values
    composite()
    assert len(made) == 3
