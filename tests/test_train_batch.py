"""Batched views (train.batch_size): one view per step is the single-view step bit for bit; a batch of two has the
mean of the two single-view gradients, gsplat's densification statistics (each view's own gradient norm, one count
per view) and the square-root Adam scaling; bad batch settings name their key."""
import math

import pytest
import torch

from train_fixtures import quick_overrides
from warpgs.config.loader import ConfigError, load_config
from warpgs.train import setup as train_setup
from warpgs.train.optim import means_lr_at, update_learning_rates
from warpgs.train.scaling import adam_settings, lr_scale
from warpgs.train.trainer import Trainer

STEPS = 18  # densification at 6 and 12, SH degree raised at 15


def _trainer(out, resume=False, **extra):
    # With the learned environment map: a module with its own optimizer, as in the default run.
    settings = {"strategy.refine_start": 5, "strategy.refine_every": 6, "eval.save_images": False,
                "extensions.environment.degree": 2}
    settings.update(extra)
    return Trainer(None, overrides=quick_overrides(out, STEPS, **settings), quiet=True, resume=resume)


def _single_view_step(tr) -> dict:
    """The trainer's step before batches existed, line for line (commit 32bfb15), on the trainer's own parts."""
    cfg, model, step = tr.config, tr.model, tr.step
    view = tr.views.next()
    batch = tr.make_batch(view, step)
    model.active_sh_degree = train_setup.active_sh_degree(step, cfg, model.max_sh_degree)
    update_learning_rates(tr.optimizer, step, cfg.optim, tr.extent, tr.max_steps)
    densify = step < cfg.strategy.refine_stop
    out = tr.render(view, tr.outputs_at(step), batch, track_means2d=densify, step=step)
    result = tr.loss_set(out, batch, model, step, tr.max_steps)
    tr.strategy.step_pre_backward(model, step)
    result.total.backward()
    tr.check_finite(step, result)
    for opt in tr.optimizers:
        opt.step()
    report = None
    if densify:
        grad2d = out.means2d.grad if out.means2d is not None else None
        report = tr.strategy.step_post_backward(model, tr.optimizer, step, visible=out.visible, viewmat=view.viewmat,
                                                K=view.K, width=view.width, height=view.height, grad2d=grad2d,
                                                near=cfg.train.near)
    for opt in tr.optimizers:
        opt.zero_grad(set_to_none=True)
    model.zero_grad(set_to_none=True)
    mse = float(((out.rgb.detach() - view.image) ** 2).mean())
    tr.counters.step = step + 1
    return {"loss": float(result.total.detach()), "mse": mse, "densify": report}


def _state(tr) -> dict:
    state = {f"param.{n}": p.detach().clone() for n, p in tr.named_parameters()}
    for i, opt in enumerate(tr.optimizers):
        for j, group in enumerate(opt.param_groups):
            for k, p in enumerate(group["params"]):
                for key, v in opt.state[p].items():
                    state[f"opt{i}.{j}.{k}.{key}"] = v.clone() if torch.is_tensor(v) else v
    for key in ("grad_accum", "count", "max_radii", "max_screen"):
        state[f"strategy.{key}"] = getattr(tr.strategy.stats, key).clone()
    return state


def test_one_view_per_step_is_the_single_view_step_bit_for_bit(tmp_path):
    batched = _trainer(tmp_path / "a")  # train.batch_size defaults to 1
    single = _trainer(tmp_path / "b")
    refines = 0
    for _ in range(STEPS):
        info = batched.train_step()
        ref = _single_view_step(single)
        assert info["loss"] == ref["loss"]
        assert info["psnr"] == 10.0 * math.log10(1.0 / max(ref["mse"], 1e-10))
        assert (info["densify"] is None) == (ref["densify"] is None)
        refines += ref["densify"] is not None
    assert refines == 2 and batched.model.num_primitives > 1500  # the comparison covered densification
    a, b = _state(batched), _state(single)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(torch.as_tensor(a[key]), torch.as_tensor(b[key])), key


def _views_drawn(tr, n):
    saved = tr.views.state_dict()
    indices = tr.views.draw(n)
    tr.views.load_state_dict(saved)
    return [tr.view(i) for i in indices]


def _single_view_grads(tr, view, step=0):
    """(loss, {name: grad}, means2d grad, visible) of one view's own loss at the current parameters."""
    tr.model.active_sh_degree = train_setup.active_sh_degree(step, tr.config, tr.model.max_sh_degree)
    batch = tr.make_batch(view, step)
    out = tr.render(view, tr.outputs_at(step), batch, track_means2d=True, step=step)
    result = tr.loss_set(out, batch, tr.model, step, tr.max_steps)
    result.total.backward()
    grads = {n: p.grad.clone() for n, p in tr.named_parameters()}
    g2d = out.means2d.grad.clone() if out.means2d is not None else None
    means_grad = tr.model.means.grad.clone()
    for _, p in tr.named_parameters():
        p.grad = None
    return float(result.total.detach()), grads, g2d, means_grad, out.visible.clone()


def test_batch_of_two_is_the_mean_of_two_single_view_steps(tmp_path):
    tr = _trainer(tmp_path / "b2", **{"train.batch_size": 2})
    views = _views_drawn(tr, 2)
    singles = [_single_view_grads(tr, v) for v in views]
    captured = {}

    def keep_grads(optimizer, args, kwargs):
        captured.update({n: p.grad.clone() for n, p in tr.named_parameters() if p.grad is not None})

    tr.optimizer.register_step_pre_hook(keep_grads)
    info = tr.train_step()  # step 0: statistics accumulate, no refine

    assert info["views"] == [v.name for v in views]
    assert info["loss"] == pytest.approx((singles[0][0] + singles[1][0]) / 2, rel=1e-6)
    for name, _ in tr.named_parameters():
        expected = (singles[0][1][name] + singles[1][1][name]) / 2
        assert torch.allclose(captured[name], expected, rtol=1e-5, atol=1e-10), name
    # gsplat's DefaultStrategy (packed=False): each view's own gradient, in NDC units (x W/2, H/2), one count per
    # view in which the primitive is visible; the batch mean's gradient times B is that view's own gradient.
    W, H = views[0].width, views[0].height
    scale = torch.tensor([0.5 * W, 0.5 * H])
    norms = [torch.where(s[4], (s[2] * scale).norm(dim=-1), torch.zeros(())) for s in singles]
    assert torch.allclose(tr.strategy.stats.grad_accum, norms[0] + norms[1], rtol=1e-4, atol=1e-9)
    assert torch.equal(tr.strategy.stats.count, singles[0][4].long() + singles[1][4].long())


def test_surfel_batches_project_each_views_share_of_the_means_gradient(tmp_path):
    # Surfels expose no 2D means: each view's own means.grad (a difference of the accumulated one) is projected.
    tr = _trainer(tmp_path / "s2", **{"train.batch_size": 2, "model.kind": "surfels"})
    views = _views_drawn(tr, 2)
    singles = [_single_view_grads(tr, v) for v in views]
    tr.train_step()
    from warpgs.train.screen_geometry import screen_grads_from_means_grad

    W, H = views[0].width, views[0].height
    scale = torch.tensor([0.5 * W, 0.5 * H])
    expected = sum(torch.where(s[4], (screen_grads_from_means_grad(tr.model.means, s[3], v.viewmat, v.K) * scale)
                               .norm(dim=-1), torch.zeros(())) for s, v in zip(singles, views))
    # Equal up to the rounding of that difference.
    assert torch.allclose(tr.strategy.stats.grad_accum, expected, rtol=1e-4, atol=1e-5 * float(expected.max()))
    assert torch.equal(tr.strategy.stats.count, singles[0][4].long() + singles[1][4].long())


def test_square_root_scaling_of_adam_and_resume_with_another_batch_size(tmp_path):
    one = _trainer(tmp_path / "r", **{"train.steps": 3})
    base = {g["name"]: g["lr"] for g in one.optimizer.param_groups}
    base_module = one.module_optimizer.param_groups[0]["lr"]
    one.fit()

    four = _trainer(tmp_path / "r", resume=True, **{"train.steps": 6, "train.batch_size": 4})
    assert four.step == 3
    for g in four.optimizer.param_groups:
        if g["name"] != "means":  # its lr follows the schedule at every step, times the same factor
            assert g["lr"] == pytest.approx(2.0 * base[g["name"]], rel=1e-12)
        assert g["eps"] == pytest.approx(1e-15 / 2) and g["betas"] == pytest.approx((0.6, 0.996))
    mod = four.module_optimizer.param_groups[0]
    assert mod["lr"] == pytest.approx(2.0 * base_module) and mod["eps"] == pytest.approx(1e-8 / 2)
    four.train_step()
    means = next(g for g in four.optimizer.param_groups if g["name"] == "means")
    assert means["lr"] == pytest.approx(2.0 * means_lr_at(3, four.config.optim, four.extent, 6), rel=1e-12)


def test_scaling_rules():
    assert lr_scale(1, "sqrt") == 1.0 and lr_scale(9, "sqrt") == 3.0 and lr_scale(9, "none") == 1.0
    assert adam_settings(1, "sqrt", 1e-15, (0.9, 0.999)) == (1e-15, (0.9, 0.999))  # untouched, no arithmetic
    eps, betas = adam_settings(16, "sqrt", 1e-15, (0.9, 0.999))
    assert eps == pytest.approx(2.5e-16) and betas == pytest.approx((0.0, 0.984))  # beta1 clamped, not negative
    assert adam_settings(16, "none", 1e-15, (0.9, 0.999)) == (1e-15, (0.9, 0.999))
    with pytest.raises(ValueError, match="train.batch_scaling"):
        lr_scale(2, "linear")


@pytest.mark.parametrize("override, key", [("train.batch_size=0", "train.batch_size"),
                                           ("batch_size=-2", "train.batch_size"),
                                           ("train.batch_scaling=linear", "train.batch_scaling"),
                                           ("train.dist_backend=mpi", "train.dist_backend"),
                                           ("train.dist_timeout=0", "train.dist_timeout")])
def test_bad_batch_settings_name_their_key(override, key):
    with pytest.raises(ConfigError) as e:
        load_config(None, [override])
    assert e.value.key == key
