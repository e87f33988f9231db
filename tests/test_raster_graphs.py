"""On a GPU the launches up to a render's sync run as a CUDA graph once the same call repeats (graph_cache.GraphCache):
images and gradients must be those of eager launches, a changed input must never replay a stale graph, and bad
input must still be named. Needs CUDA (the CPU has no graphs); run with a GPU: pytest tests/test_raster_graphs.py."""
import pytest
import torch

from random_scenes import random_scene
from warpgs import rasterize, rasterize_surfels
from warpgs.render import device_state, graph_cache

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")


def _scene(n=3000, seed=0):
    s = random_scene(n=n, seed=seed, width=96, height=64)
    return {k: (v.float().cuda() if isinstance(v, torch.Tensor) else v) for k, v in s.items()}


def _render(s, surfels=False, **kw):
    leaves = [s[k].detach().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")]
    if surfels:
        leaves[2] = leaves[2][:, :2].detach().requires_grad_(True)
    op = rasterize_surfels if surfels else rasterize
    out = op(*leaves, s["viewmat"], s["K"], s["width"], s["height"], outputs=("rgb", "alpha", "depth"), **kw)
    (out.rgb.sum() + out.depth.sum()).backward()
    return [out.rgb.detach(), out.alpha.detach(), out.depth.detach()] + [t.grad for t in leaves]


def _graphs():
    return device_state.device_state(torch.device("cuda", torch.cuda.current_device())).ws.graphs


@pytest.mark.parametrize("surfels", [False, True])
def test_graph_replays_match_eager_launches(monkeypatch, surfels):
    s = _scene()
    monkeypatch.setattr(graph_cache, "GRAPHS_ENABLED", False)
    eager = _render(s, surfels)
    monkeypatch.setattr(graph_cache, "GRAPHS_ENABLED", True)
    graphs = _graphs()
    replays = graphs.replays
    runs = [_render(s, surfels) for _ in range(4)]
    assert not graphs.broken and graphs.replays > replays  # captured on the second call, replayed after
    for run in runs:
        for a, b in zip(eager, run):
            assert torch.allclose(a, b, atol=1e-5, rtol=1e-4)  # forward exact; gradients up to atomics' order
        assert torch.equal(run[0], eager[0])


def test_changed_inputs_are_not_served_a_stale_graph():
    s, t = _scene(seed=0), _scene(seed=1)
    for _ in range(3):
        a = _render(s)
    b = _render(t)  # other tensors: another key
    s["means"].copy_(t["means"])  # same tensor, new contents: the graph reads memory, so it must follow
    for k in ("quats", "scales", "opacities", "colors"):
        s[k].copy_(t[k])
    c = _render(s)
    assert not torch.equal(a[0], b[0]) and torch.equal(b[0], c[0])


@pytest.mark.parametrize("surfels", [False, True])
def test_bad_input_named_while_graphs_replay(surfels):
    s = _scene()
    for _ in range(3):
        _render(s, surfels)
    s["scales"][17, 1] = float("nan")  # same tensors, so the replayed graph's check kernel must catch it
    with pytest.raises(ValueError, match="^scales contains NaN or Inf"):
        _render(s, surfels)
    s["scales"][17, 1] = 0.01
    s["opacities"][5] = 2.0
    with pytest.raises(ValueError, match="opacities must lie in"):
        _render(s, surfels)


def test_captures_leave_other_threads_default_stream_work_alone():
    """Graphs are captured on a non-blocking stream: torch work on the legacy default stream in another thread
    (a viewer beside the trainer, say) must not fail while this thread captures."""
    import threading

    from warpgs.render.device_state import release_workspaces

    s = _scene()
    reference = _render(s)[0]
    failures, stop = [], threading.Event()

    def other_thread():
        try:
            while not stop.is_set():
                (torch.randn(4096, device="cuda") * 2.0).sum().item()
        except Exception as exc:  # noqa: BLE001 - reported below
            failures.append(exc)

    worker = threading.Thread(target=other_thread)
    worker.start()
    try:
        for _ in range(10):
            release_workspaces()  # fresh graph caches: the second render of each pair captures
            _render(s)
            assert torch.equal(_render(s)[0], reference)
    finally:
        stop.set()
        worker.join()
    assert not failures, failures


@pytest.mark.parametrize("surfels", [False, True])
def test_the_views_of_a_training_run_share_one_graph(monkeypatch, surfels):
    """Each call's camera is copied into the op's own buffers before the graphed launches, so views that follow each
    other (every step of a training run) replay one graph and each gets its own image."""
    s = _scene()
    views = []
    for i in range(3):
        v = s["viewmat"].clone()
        v[0, 3] += 0.2 * i  # another camera in another tensor, as each training view holds its own
        views.append(dict(s, viewmat=v, K=s["K"].clone()))
    monkeypatch.setattr(graph_cache, "GRAPHS_ENABLED", False)
    eager = [_render(v, surfels) for v in views]
    monkeypatch.setattr(graph_cache, "GRAPHS_ENABLED", True)
    graphs = _graphs()
    replays = graphs.replays
    for _ in range(3):
        for v, want in zip(views, eager):
            got = _render(v, surfels)
            assert torch.equal(got[0], want[0])
    assert not graphs.broken and graphs.replays - replays >= 6  # one capture, then replays across the views


def test_graphs_captured_before_the_sort_scratch_grew_are_not_replayed(monkeypatch):
    """A larger render's sorts make the capture stream's radix-sort scratch grow (Warp frees the old one): graphs
    captured before are dropped, so none sorts in freed memory, and the small scene still renders as it did."""
    from warpgs.render.device_state import release_workspaces

    release_workspaces()
    small, large = _scene(n=500, seed=2), _scene(n=20000, seed=3)
    monkeypatch.setattr(graph_cache, "GRAPHS_ENABLED", False)
    want = _render(small)[0]
    monkeypatch.setattr(graph_cache, "GRAPHS_ENABLED", True)
    for _ in range(3):
        _render(small)
    graphs = _graphs()
    room = graphs.sort_room
    assert room > 0 and graphs.captures > 0
    for _ in range(3):
        _render(large)
    assert graphs.sort_room > room  # grew, and dropped what was captured on the smaller scratch
    for _ in range(3):
        assert torch.equal(_render(small)[0], want)
    assert not graphs.broken
