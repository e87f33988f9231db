"""ShapeGraphs (warpgs/losses/cuda_graphs.py): which calls replay from a graph, one graph per signature, a cap.
CI has no GPU, so the capture is a stand-in that records what it was given; the graphs themselves are checked
against the plain SSIM on a GPU by benchmarks/ssim_loss.py."""
import pytest
import torch

from warpgs.losses import cuda_graphs
from warpgs.losses.cuda_graphs import KeyedGraphs, ShapeGraphs, loss_graphs_enabled
from warpgs.metrics.image import ssim


class RecordingCapture:
    def __init__(self):
        self.samples = []

    def __call__(self, fn, sample):
        self.samples.append(sample)
        return lambda *args: ("replayed", fn(*args))


def images(h, w, grad=True):
    pred = torch.rand(h, w, 3, requires_grad=grad)
    return pred, torch.rand(h, w, 3)


def test_one_graph_per_signature_and_samples_are_copies():
    capture = RecordingCapture()
    graphs = ShapeGraphs(ssim, capture=capture)
    pred, target = images(16, 12)
    for _ in range(3):
        tag, value = graphs.lookup((pred, target))(pred, target)
        assert tag == "replayed"
        assert torch.allclose(value, ssim(pred, target))
    assert len(capture.samples) == 1
    sample_pred, sample_target = capture.samples[0]
    assert sample_pred.requires_grad and not sample_target.requires_grad
    assert sample_pred.data_ptr() != pred.data_ptr() and sample_pred.grad_fn is None  # a leaf copy
    graphs.lookup(images(8, 12))  # another shape: a second graph
    graphs.lookup((pred.detach(), target))  # the same shape without grad: another signature
    assert len(capture.samples) == 3 and len(graphs.graphs) == 3


def test_past_max_graphs_the_function_runs_as_written():
    capture = RecordingCapture()
    graphs = ShapeGraphs(ssim, max_graphs=2, capture=capture)
    graphs.lookup(images(8, 8))
    graphs.lookup(images(9, 8))
    assert graphs.lookup(images(10, 8)) is ssim
    assert len(capture.samples) == 2


def test_cpu_and_evaluation_calls_never_capture():
    capture = RecordingCapture()
    graphs = ShapeGraphs(ssim, capture=capture)
    pred, target = images(16, 16)
    out = graphs(pred, target)  # CPU tensors: the plain function
    assert torch.equal(out, ssim(pred, target)) and out.requires_grad
    with torch.no_grad():
        graphs(pred, target)
    assert capture.samples == [] and graphs.graphs == {}


@pytest.mark.parametrize("value,enabled", [("0", False), ("off", False), ("1", True), (None, True)])
def test_environment_switch(monkeypatch, value, enabled):
    if value is None:
        monkeypatch.delenv("WARPGS_LOSS_GRAPHS", raising=False)
    else:
        monkeypatch.setenv("WARPGS_LOSS_GRAPHS", value)
    assert loss_graphs_enabled() is enabled


def test_torch_dssim_goes_through_the_graphs_wrapper():
    from warpgs.losses import photometric

    assert isinstance(photometric._graphed_ssim, ShapeGraphs) and photometric._graphed_ssim.fn is ssim
    assert cuda_graphs._is_training_call((torch.zeros(1, requires_grad=True),)) is False  # CPU


def test_keyed_graphs_make_a_function_a_key_and_keep_the_keys_used_last():
    capture, made = RecordingCapture(), []

    def make(key):
        made.append(key)
        return lambda pred, target: ssim(pred, target) * key

    graphs = KeyedGraphs(make, max_keys=2, capture=capture)
    pred, target = images(8, 8)
    for key in (1.0, 2.0, 1.0, 3.0, 1.0):
        tag, value = graphs.graphs_for(key).lookup((pred, target))(pred, target)
        assert tag == "replayed" and torch.allclose(value, ssim(pred, target) * key)
    assert made == [1.0, 2.0, 3.0] and list(graphs.keys) == [3.0, 1.0]  # 3.0 dropped 2.0, used least recently
    assert len(capture.samples) == 3
    out = graphs(2.0, pred, target)  # CPU: the function made for the key, as written (2.0 made again)
    assert torch.allclose(out, ssim(pred, target) * 2.0) and len(capture.samples) == 3
    assert made[-1] == 2.0 and list(graphs.keys) == [1.0, 2.0]


def test_a_failed_capture_warns_and_runs_the_function_as_written():
    calls = []

    def failing(fn, sample):
        calls.append(sample)
        raise RuntimeError("operation not permitted when stream is capturing")

    graphs = ShapeGraphs(ssim, capture=failing)
    pred, target = images(16, 12)
    with pytest.warns(RuntimeWarning, match="capture failed"):
        assert graphs.lookup((pred, target)) is ssim
    assert graphs.lookup((pred, target)) is ssim and len(calls) == 1  # not tried again for these inputs
