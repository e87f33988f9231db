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
