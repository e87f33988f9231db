"""The sparse-view presets: they load, share everything but the loss terms, and each ablation drops exactly its
term (and the depth render outputs only when no depth term is left)."""
from pathlib import Path

import pytest

from warpgs.config.loader import load_config
from warpgs.losses import required_outputs, resolve_losses

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
TERMS = ("depth", "depth_grad", "depth_local", "opacity", "scale", "count")


def load(name, *overrides):
    return load_config(CONFIGS / f"sparse_{name}.yaml", list(overrides))


def test_method_preset_is_the_paper_objective():
    cfg = load("lightfield")
    terms = {t.name: t for t in resolve_losses(cfg.losses)}
    assert list(terms) == ["l1", "dssim", *TERMS]
    assert terms["l1"].weight == 0.8 and terms["dssim"].weight == 0.2
    assert (terms["opacity"].weight, terms["scale"].weight, terms["count"].weight) == (0.05, 0.008, 0.001)
    for name in TERMS[:3]:
        assert terms[name].weight_at(0, cfg.train.steps) == pytest.approx(1.0)
        assert terms[name].weight_at(cfg.train.steps, cfg.train.steps) == pytest.approx(0.01)
    assert cfg.train.steps == 30_000 and cfg.data.synthetic == "lightfield" and cfg.data.depth_priors == "auto"
    assert required_outputs(terms.values()) == ("rgb", "alpha", "inv_depth")


def test_baseline_differs_only_in_losses():
    base, method = load("baseline"), load("lightfield")
    assert [t.name for t in resolve_losses(base.losses)] == ["l1", "dssim"]
    assert required_outputs(resolve_losses(base.losses)) == ("rgb",)
    a, b = base.to_dict(), method.to_dict()
    a.pop("losses"), b.pop("losses")
    assert a == b


@pytest.mark.parametrize("term", TERMS)
def test_each_ablation_drops_exactly_its_term(term):
    cfg = load(f"wo_{term}")
    names = [t.name for t in resolve_losses(cfg.losses)]
    assert names == ["l1", "dssim", *[t for t in TERMS if t != term]]
    assert required_outputs(resolve_losses(cfg.losses)) == ("rgb", "alpha", "inv_depth")
    a, b = cfg.to_dict(), load("lightfield").to_dict()
    a.pop("losses"), b.pop("losses")
    assert a == b


def test_all_depth_terms_off_renders_no_depth():
    cfg = load("lightfield", "losses.depth=0", "losses.depth_grad=0", "losses.depth_local=0")
    assert required_outputs(resolve_losses(cfg.losses)) == ("rgb",)
