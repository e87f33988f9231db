"""The Marr depth terms replayed from CUDA graphs (warpgs/losses/marr.py over cuda_graphs.KeyedGraphs): which calls
go through the graphs and with which arguments, the graphed core against the terms as they were, settings, and the
kept values. CI has no GPU: the capture is a stand-in that keeps the graphs' contract on the CPU (the sample's
tensors are the static inputs each call copies into; the output is one buffer each call overwrites); the real
graphs are checked against the eager terms on a GPU by benchmarks/marr_graphs.py."""
import json
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from warpgs.losses import compute_losses, cuda_graphs, get_loss, marr, resolve_losses
from warpgs.losses.cuda_graphs import KeyedGraphs

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import marr_graphs  # noqa: E402 - benchmarks/marr_graphs.py

MARR = ("depth", "depth_grad", "depth_local")


class StaticGraphs:
    """A stand-in for torch.cuda.make_graphed_callables with its contract: inputs copied into the sample's tensors,
    the output one buffer per graph, the backward differentiating the graph's last call."""

    def __init__(self):
        self.samples, self.replays = [], 0

    def __call__(self, fn, sample):
        self.samples.append(sample)
        state, stand_in = {}, self

        class Replay(torch.autograd.Function):
            @staticmethod
            def forward(ctx, *args):
                stand_in.replays += 1
                with torch.no_grad():
                    for static, arg in zip(sample, args):
                        static.copy_(arg)
                with torch.enable_grad():
                    state["out"] = fn(*sample)
                buffer = state.setdefault("buffer", torch.empty_like(state["out"]))
                buffer.copy_(state["out"].detach())
                return buffer.detach()

            @staticmethod
            def backward(ctx, grad):
                wanted = [s for s in sample if s.requires_grad]
                grads = iter(torch.autograd.grad(state["out"], wanted, grad))
                return tuple(next(grads) if s.requires_grad else None for s in sample)

        return lambda *args: Replay.apply(*args)


@pytest.fixture
def capture(monkeypatch):
    """Graphs for CPU training calls, through the stand-in (the real ones are CUDA only)."""
    stand_in = StaticGraphs()
    monkeypatch.delenv("WARPGS_LOSS_GRAPHS", raising=False)
    monkeypatch.setattr(cuda_graphs, "_is_training_call",
                        lambda args: torch.is_grad_enabled() and args[0].requires_grad)
    for name in MARR:
        monkeypatch.setitem(marr._GRAPHS, name, KeyedGraphs(marr._GRAPHS[name].make, capture=stand_in))
    return stand_in


def inputs(seed=0, h=16, w=20, dtype=torch.float32, confidence=True, mask=False):
    """A render and a batch as the trainer makes them: the prior and its valid mask in the batch, the confidence on
    its view; with NaN and non-positive prior pixels, invalid ones, alpha below alpha_min, zero confidence."""
    g = torch.Generator().manual_seed(seed)
    alpha = torch.rand(h, w, 1, generator=g, dtype=dtype) * 1.1
    alpha[0, :3] = 0.05  # below alpha_min
    inv = (alpha * (0.2 + torch.rand(h, w, 1, generator=g, dtype=dtype))).requires_grad_(True)
    alpha.requires_grad_(True)
    prior = 0.2 + torch.rand(h, w, 1, generator=g)
    prior[1, 1], prior[2, 5] = float("nan"), -0.1
    valid = torch.rand(h, w, 1, generator=g) > 0.05
    view = SimpleNamespace(inv_depth_confidence=None)
    if confidence:
        view.inv_depth_confidence = torch.rand(h, w, 1, generator=g)
        view.inv_depth_confidence[4:6, 4:7] = 0.0
    batch = {"inv_depth_prior": prior, "inv_depth_valid": valid, "view": view}
    if mask:
        batch["mask"] = torch.rand(h, w, 1, generator=g) > 0.05
    return SimpleNamespace(inv_depth=inv, alpha=alpha), batch


def reference(name, out, batch, alpha_eps=1e-6, alpha_min=0.1, power=1.0):
    """The term as marr.py computed it before the graphs (one eager function of the render and the batch)."""
    bchw = lambda t: t.permute(2, 0, 1)[None]  # noqa: E731 - [H, W, 1] -> [1, 1, H, W]
    inv, alpha = bchw(out.inv_depth), bchw(out.alpha)
    pred = inv / alpha.clamp_min(alpha_eps)
    prior = bchw(batch["inv_depth_prior"]).to(pred)
    keep = torch.isfinite(prior) & (prior > 0) & bchw(batch["inv_depth_valid"])
    if "mask" in batch:
        keep = keep & bchw(batch["mask"])
    if alpha_min > 0:
        keep = keep & (alpha.detach() >= alpha_min)
    prior = torch.where(keep, prior, torch.zeros_like(prior))
    conf = batch["view"].inv_depth_confidence
    weight = None if conf is None or power == 0 else bchw(conf).to(pred).clamp(0.0, 1.0).pow(power)
    return marr.TERMS[name](pred, prior, keep, weight)


def value_and_grads(loss, out):
    return (loss.detach(),) + torch.autograd.grad(loss, (out.inv_depth, out.alpha))


def test_training_call_replays_a_graph_with_the_trainers_signature(capture):
    out, batch = inputs()
    for name in MARR:
        get_loss(name).fn(out, batch, None, 0).backward()
    assert capture.replays == 3 and len(capture.samples) == 3  # one graph a term
    for sample in capture.samples:  # inv_depth, alpha, prior, valid, confidence: [1, 1, H, W] each
        assert [tuple(t.shape) for t in sample] == [(1, 1, 16, 20)] * 5
        assert [t.dtype for t in sample] == [torch.float32] * 3 + [torch.bool, torch.float32]
        assert [t.requires_grad for t in sample] == [True, True, False, False, False]
    for name in MARR:  # another view of the same size: the same graphs
        get_loss(name).fn(*inputs(seed=1), None, 0)
    assert capture.replays == 6 and len(capture.samples) == 3
    get_loss("depth").fn(*inputs(confidence=False), None, 0)  # no confidence: another signature
    get_loss("depth").fn(*inputs(mask=True), None, 0)  # a batch mask too: another
    assert [len(s) for s in capture.samples[3:]] == [4, 6]


def test_evaluation_cpu_and_switched_off_calls_run_the_terms_as_written(capture, monkeypatch):
    out, batch = inputs()
    with torch.no_grad():
        for name in MARR:
            get_loss(name).fn(out, batch, None, 0)
    for name in MARR:
        get_loss(name).fn(SimpleNamespace(inv_depth=out.inv_depth.detach(), alpha=out.alpha), batch, None, 0)
    monkeypatch.setenv("WARPGS_LOSS_GRAPHS", "0")
    get_loss("depth").fn(out, batch, None, 0)
    assert capture.replays == 0 and capture.samples == []
    monkeypatch.undo()  # the real test of a training call: CUDA tensors only
    assert not cuda_graphs._is_training_call((out.inv_depth, out.alpha))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed,confidence,mask", [(0, True, False), (1, True, True), (2, False, False),
                                                  (3, False, True)])
def test_graphed_terms_equal_the_eager_terms(capture, dtype, seed, confidence, mask):
    out, batch = inputs(seed, dtype=dtype, confidence=confidence, mask=mask)
    for name in MARR:
        got = value_and_grads(get_loss(name).fn(out, batch, None, 0), out)
        want = value_and_grads(reference(name, out, batch), out)
        for a, b in zip(got, want):
            assert a.dtype == dtype and torch.equal(a, b), name
        assert got[0] > 0 and got[1].abs().sum() > 0 and got[2].abs().sum() > 0
    assert capture.replays == 3


def test_eager_path_equals_the_terms_as_they_were():
    out, batch = inputs(4, mask=True)
    for name in MARR:
        got = value_and_grads(get_loss(name).fn(out, batch, None, 0), out)
        for a, b in zip(got, value_and_grads(reference(name, out, batch), out)):
            assert torch.equal(a, b), name


def test_settings_changes_reach_the_graphed_terms(capture):
    out, batch = inputs(5)
    saved = (marr.SETTINGS.alpha_eps, marr.SETTINGS.alpha_min, marr.SETTINGS.confidence_power)
    try:
        for settings in ((1e-6, 0.1, 1.0), (1e-6, 0.0, 1.0), (0.2, 0.3, 2.0), (1e-6, 0.1, 0.0), (1e-6, 0.1, 1.0)):
            marr.configure(alpha_eps=settings[0], alpha_min=settings[1], confidence_power=settings[2])
            for name in MARR:
                got = value_and_grads(get_loss(name).fn(out, batch, None, 0), out)
                want = value_and_grads(reference(name, out, batch, *settings), out)
                assert all(torch.equal(a, b) for a, b in zip(got, want)), (name, settings)
    finally:
        marr.configure(alpha_eps=saved[0], alpha_min=saved[1], confidence_power=saved[2])
    assert capture.replays == 15
    # each new setting a graph; the last is the first again, whose graphs were dropped (two kept a term)
    assert len(capture.samples) == 15
    assert [len(s) for s in capture.samples[9:12]] == [4] * 3  # confidence_power 0: no confidence map


def test_kept_values_survive_the_next_replay(capture):
    """compute_losses keeps each term's value (read a step later): not a view of the graph's buffer."""
    terms = resolve_losses({name: 1.0 for name in MARR})
    first = compute_losses(terms, *inputs(6), None, 0, 100)
    kept = {k: v.clone() for k, v in first.values.items()}
    compute_losses(terms, *inputs(7), None, 0, 100)  # the next view: every graph replays
    assert capture.replays == 6
    assert all(torch.equal(first.values[k], kept[k]) for k in MARR)


def test_the_confidence_check_stays_outside_the_graph(capture):
    out, batch = inputs(8)
    batch["view"].inv_depth_confidence[3, 3] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        get_loss("depth").fn(out, batch, None, 0)
    assert capture.samples == []
    # the core itself reads nothing on the host: it takes the NaN map without a check
    core = marr.term_core("depth", marr.current_settings(), True)
    args = marr.checked_maps(out, {k: v for k, v in batch.items() if k != "view"}, marr.current_settings())
    conf = batch["view"].inv_depth_confidence.permute(2, 0, 1)[None]
    assert torch.isnan(core(*args[:3], *args[3], conf))


def test_the_gpu_benchmark_runs_on_the_cpu(tmp_path, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path))
    monkeypatch.delenv("WARPGS_LOSS_GRAPHS", raising=False)
    assert marr_graphs.main(["--sizes", "12x10", "--calls", "2", "--rounds", "1", "--device", "cpu", "--tag", "t"]) == 0
    result = json.loads((tmp_path / "marr_graphs_cpu_t.json").read_text())
    assert result["ok"] and not result["graphs"] and "WARPGS_LOSS_GRAPHS" not in os.environ
    row = result["rows"][0]
    assert set(row["checks"]) == {"trainer", "no_confidence", "batch_mask", "settings", "trainer_again", "kept_values"}
    assert set(row["timings"]) == {"depth", "depth_grad", "depth_local", "all"}
