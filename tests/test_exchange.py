"""exchange_rows on two gloo processes: blocks of different sizes (empty ones too) reach their ranks whole and in
rank order, and the backward returns each received block's gradient to the rows that sent it."""
import torch

from gloo_helpers import run_two_ranks

WORKER = r'''
import sys, torch, torch.distributed as dist
from gloo_helpers import end_worker
from warpgs.render.exchange import exchange_rows
dist.init_process_group("gloo")
rank = dist.get_rank()
sizes = {0: [3, 0], 1: [5, 2]}[rank]  # rank 0 sends nothing to rank 1
rows = torch.arange(sum(sizes) * 4, dtype=torch.float32).reshape(-1, 4) + 1000 * rank
rows.requires_grad_(True)
received = exchange_rows(list(rows.split(sizes)), None)
weights = torch.cat([torch.full((len(b), 4), float(10 * j + rank + 1)) for j, b in enumerate(received)])
(torch.cat(received) * weights).sum().backward()
torch.save({"received": [b.detach() for b in received], "grad": rows.grad, "rows": rows.detach()},
           sys.argv[1] + f".rank{rank}")
end_worker()
'''


def test_uneven_and_empty_blocks_go_and_come_back(tmp_path):
    run_two_ranks(WORKER, [tmp_path / "x"], tmp_path)
    r0, r1 = (torch.load(tmp_path / f"x.rank{r}") for r in (0, 1))
    # Rank 0 receives its own first block (3 rows) and rank 1's first (5 rows); rank 1 gets 0 rows from rank 0.
    assert [len(b) for b in r0["received"]] == [3, 5] and [len(b) for b in r1["received"]] == [0, 2]
    assert torch.equal(r0["received"][0], r0["rows"][:3]) and torch.equal(r0["received"][1], r1["rows"][:5])
    assert torch.equal(r1["received"][1], r1["rows"][5:])
    # Gradients: the receiver weighted the block from rank j by 10 j + receiver + 1; each sender's rows get the
    # weight of the rank they went to.
    assert bool((r0["grad"] == 1.0).all())  # its 3 rows went to rank 0 (from rank 0: 10*0 + 0 + 1)
    assert bool((r1["grad"][:5] == 11.0).all()) and bool((r1["grad"][5:] == 12.0).all())
