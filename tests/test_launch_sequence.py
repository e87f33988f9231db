"""workspace.LaunchSequence: the launches up to a render's sync, issued together (one CUDA graph on GPUs when the
same sequence comes again). The graph is only valid if its key changes whenever anything it bakes in changes; the
keys and the reads are checked here on the CPU (graphs themselves: tests/test_raster_graphs.py, on a GPU)."""
import numpy as np
import warp as wp

from warpgs.kernels import binning
from warpgs.render.workspace import Workspace


def _sequence(ws, a, b, n, dim=None):
    seq = ws.sequence()
    seq.launch("counts_in_order", binning.counts_in_order, n if dim is None else dim, [a, b, ws.array("out", n,
                                                                                                     wp.int32)])
    seq.scan(ws.array("out", n, wp.int32), ws.array("sums", n, wp.int32))
    return seq


def test_reads_come_back_in_order_and_checks_see_them():
    ws = Workspace("cpu")
    order = wp.array(np.arange(5, dtype=np.int32)[::-1].copy(), device="cpu")
    counts = wp.array(np.array([1, 2, 3, 4, 5], dtype=np.int32), device="cpu")
    seq = _sequence(ws, order, counts, 5)
    total = seq.read_ints(ws.array("sums", 5, wp.int32), 4)
    both = seq.read_ints(counts, 1, 2)
    seen = []
    seq.on_values(seen.append)
    values = seq.run()
    assert values[total] == 15 and values[both: both + 2] == [2, 3] and seen == [values]


def test_key_follows_every_baked_in_value():
    ws = Workspace("cpu")
    a = wp.zeros(8, dtype=wp.int32, device="cpu")
    b = wp.zeros(8, dtype=wp.int32, device="cpu")
    c = wp.zeros(8, dtype=wp.int32, device="cpu")

    def key(seq):
        seq._host = _HOST  # where a GPU run copies its reads (set by run)
        return seq._key()[0]

    same = key(_sequence(ws, a, b, 8))
    assert key(_sequence(ws, a, b, 8)) == same  # same arrays, sizes and arguments: the graph may replay
    assert key(_sequence(ws, a, c, 8)) != same  # another input array
    assert key(_sequence(ws, a, b, 8, dim=7)) != same  # another launch size
    assert key(_sequence(ws, a[:7], b, 8)) != same  # a shorter view of the same memory
    assert key(_sequence(ws, a, b, 6)) != same  # workspace views of another size


_HOST = wp.empty(4, dtype=wp.int32, device="cpu")


def test_a_graph_captured_before_the_sort_scratch_grows_is_dropped(monkeypatch):
    """Warp replaces a stream's radix-sort scratch (freeing the old one) when a sort needs more; a graph captured
    before would sort in freed memory. GraphCache grows the capture stream's scratch before capturing a larger sort,
    to twice its size, and drops the graphs captured before. (The capture itself needs a GPU: stubbed here.)"""
    import contextlib
    from types import SimpleNamespace

    from warpgs.render import graph_cache

    cache = graph_cache.GraphCache(SimpleNamespace(stream=None, is_cuda=True))
    cache.stream_factory = lambda: "capture stream"
    grown, launched = [], []
    monkeypatch.setattr(cache, "_grow_sort_scratch", grown.append)
    monkeypatch.setattr(graph_cache.wp, "ScopedStream", lambda *a, **k: contextlib.nullcontext())
    monkeypatch.setattr(graph_cache.wp, "ScopedCapture",
                        lambda **k: contextlib.nullcontext(SimpleNamespace(graph=object())))
    monkeypatch.setattr(graph_cache.wp, "capture_launch", lambda graph, stream=None: launched.append(graph))

    def run_twice(key, largest):  # the second sight captures
        for _ in range(2):
            cache.run(key, [], lambda: None, lambda: largest)

    run_twice("small", 1000)
    assert grown == [2000] and cache.sort_room == 2000 and cache.captures == 1
    run_twice("medium", 1800)  # fits the room: nothing grows, both graphs kept
    assert grown == [2000] and len(cache._graphs) == 2
    run_twice("large", 5000)
    assert grown == [2000, 10000] and list(cache._graphs) == ["large"]  # the two captured before are gone
    cache.run("small", [], lambda: None, lambda: 1000)  # seen again: launched eagerly, not from the dropped graph
    assert cache.replays == 0 and len(launched) == 3
    run_twice("unsorted", 0)
    assert grown == [2000, 10000] and len(cache._graphs) == 2
    assert graph_cache.sort_room_for(0, 0) is None and graph_cache.sort_room_for(10, 11) == 22


def test_a_failed_scratch_reservation_falls_back_to_eager_launches(monkeypatch):
    """Growing the sort scratch runs where a capture would: if it fails, the render still runs (eagerly, warned),
    as for a failed capture."""
    from types import SimpleNamespace

    import pytest

    from warpgs.render import graph_cache

    cache = graph_cache.GraphCache(SimpleNamespace(stream=None, is_cuda=True))
    cache.stream_factory = lambda: "capture stream"

    def fail(room):
        raise RuntimeError("out of memory")

    monkeypatch.setattr(cache, "_grow_sort_scratch", fail)
    issued = []
    with pytest.warns(RuntimeWarning, match="rendering without graphs"):
        for _ in range(2):
            cache.run("key", [], lambda: issued.append(1), lambda: 1000)
    assert issued == [1, 1] and cache.broken and cache.captures == 0
