"""Model-parallel training (warpgs/train/model_parallel.py) on two gloo processes: each rank owns half of the
primitives and one camera; after a few optimizer steps the gathered model equals one process training the whole
model on both cameras with the same summed loss, and sharding then gathering a model gives it back."""
import math

import torch

from gloo_helpers import run_two_ranks
from random_scenes import look_at, random_scene
from warpgs import rasterize
from warpgs.model.gaussians import GaussianModel
from warpgs.train.distributed import Ranks
from warpgs.train.model_parallel import gather_model, shard_model

STEPS, LR = 4, 0.05


def start_model(seed: int = 7) -> GaussianModel:
    s = random_scene(n=60, sh_degree=1, seed=seed)
    logit = torch.log(s["opacities"] / (1 - s["opacities"]))
    sh0, shN = s["colors"][:, :1], s["colors"][:, 1:]
    return GaussianModel(s["means"].float(), s["scales"].log().float(), s["quats"].float(), logit.float(),
                         sh0.float(), shN.float(), active_sh_degree=1)


def cameras():
    s = random_scene(n=1)
    viewmats = torch.stack([s["viewmat"], look_at((1.2, -0.4, -3.6), (0.0, 0.1, 0.0))]).float()
    return viewmats, s["K"].float().expand(2, 3, 3).contiguous(), s["width"], s["height"]


def targets():
    """What the views should show: another random model's images, the same in every process."""
    viewmats, Ks, w, h = cameras()
    other = start_model(seed=11).render_inputs()
    with torch.no_grad():
        return [rasterize(viewmat=viewmats[r], K=Ks[r], width=w, height=h, outputs=("rgb",), **other).rgb
                for r in (0, 1)]


WORKER = r'''
import sys, torch, torch.distributed as dist
from gloo_helpers import end_worker
from test_model_parallel import LR, STEPS, cameras, start_model, targets
from warpgs.train.distributed import Ranks
from warpgs.train.model_parallel import gather_model, render_shard, shard_model
dist.init_process_group("gloo")
ranks = Ranks(dist.get_rank(), dist.get_world_size(), backend="gloo")
shard = shard_model(start_model(), ranks)
opt = torch.optim.SGD(shard.parameters(), lr=LR)
viewmats, Ks, w, h = cameras()
target = targets()[ranks.rank]
for _ in range(STEPS):
    out = render_shard(shard, viewmats, Ks, w, h, outputs=("rgb",))
    loss = (out.rgb - target).abs().mean() / 2   # this rank's view of the two-view mean
    opt.zero_grad()
    loss.backward()
    opt.step()
whole = gather_model(shard, ranks)
if ranks.rank == 0:
    torch.save({n: p.detach() for n, p in whole.params.items()}, sys.argv[1])
end_worker()
'''


def test_two_shards_train_as_one_model(tmp_path):
    run_two_ranks(WORKER, [tmp_path / "trained.pt"], tmp_path)
    got = torch.load(tmp_path / "trained.pt")

    model = start_model()
    opt = torch.optim.SGD(model.parameters(), lr=LR)
    viewmats, Ks, w, h = cameras()
    want_images = targets()
    for _ in range(STEPS):
        loss = 0.0
        for r in (0, 1):
            out = rasterize(viewmat=viewmats[r], K=Ks[r], width=w, height=h, outputs=("rgb",), **model.render_inputs())
            loss = loss + (out.rgb - want_images[r]).abs().mean() / 2
        opt.zero_grad()
        loss.backward()
        opt.step()
    start = start_model()
    moved = 0.0
    for name, p in model.params.items():
        torch.testing.assert_close(got[name], p.detach(), atol=2e-5, rtol=1e-4, msg=name)
        moved = max(moved, float((p.detach() - start.params[name].detach()).abs().max()))
    assert moved > 1e-3  # the steps changed the model, so the comparison tests the training


def test_shards_gather_back_into_the_model():
    model = start_model()
    one = Ranks()  # one process: its shard is the whole model
    again = gather_model(shard_model(model, one), one)
    for name, p in model.params.items():
        assert torch.equal(again.params[name], p)
    # The shards of two ranks cover the rows once, in order.
    parts = [shard_model(model, Ranks(rank=r, world_size=2)) for r in (0, 1)]
    assert [p.num_primitives for p in parts] == [30, 30]
    assert torch.equal(torch.cat([p.means for p in parts]), model.means)
    assert math.isclose(float(parts[1].opacities[0].detach()), float(model.opacities[30].detach()))


SCENES = r'''
import torch


def random_scene(n, width, height, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * torch.tensor([1.0, 0.6, 0.5]) + torch.tensor([0.0, 0.0, 4.0])
    quats, scales = torch.randn(n, 4, generator=g), torch.rand(n, 3, generator=g) * 0.05 + 0.01
    opacities, colors = torch.rand(n, generator=g) * 0.9 + 0.05, torch.rand(n, 3, generator=g)
    f = float(width)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    out = [t.to(device) for t in (means, quats, scales, opacities, colors, torch.eye(4), K)]
    return (*out, width, height)
'''

BENCH = r'''
import sys
sys.argv = ["sharded_render.py", "--device", "cpu", "--primitives", "400", "--size", "64x48", "--rounds", "1",
            "--tag", "test"]
import runpy
runpy.run_path(SCRIPT, run_name="__main__")
'''


def test_the_sharded_render_benchmark_runs_on_two_gloo_ranks(tmp_path, monkeypatch):
    import json
    from pathlib import Path

    script = Path(__file__).resolve().parent.parent / "benchmarks" / "sharded_render.py"
    monkeypatch.setenv("OUT", str(tmp_path))
    # The benchmark's scenes come from ../shared/bench, which a CI checkout lacks: a stand-in with the same call.
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "scenes.py").write_text(SCENES)
    monkeypatch.setenv("WARPGS_BENCH_SCENES", str(tmp_path / "bench"))
    run_two_ranks(BENCH.replace("SCRIPT", repr(str(script))), [], tmp_path)
    result = json.loads((tmp_path / "sharded_render_cpu_test.json").read_text())
    assert result["ranks"] == 2 and len(result["per_rank"]) == 2
    assert [r["primitives"] for r in result["per_rank"]] == [200, 200]
    rows = sum(sum(r["rows_sent_to"]) for r in result["per_rank"])
    assert 0 < rows and result["bytes_sent_per_step"] == rows * result["splat_bytes"]


TERMS_WORKER = r'''
import sys, torch, torch.distributed as dist
from gloo_helpers import end_worker
from test_model_parallel import start_model
from warpgs.losses import gestalt
from warpgs.train.distributed import Ranks
from warpgs.train.model_parallel import shard_training
from warpgs.train.optim import build_optimizer
from warpgs.train.strategy import DensifyStrategy
dist.init_process_group("gloo")
ranks = Ranks(dist.get_rank(), dist.get_world_size(), backend="gloo")
model = start_model()
strategy = DensifyStrategy()
strategy.initialize(model)
shard_training(model, build_optimizer(model), strategy, ranks)
result = {}
for name in ("opacity", "scale", "count"):
    model.zero_grad()
    value = getattr(gestalt, name)(None, {}, model, 0)
    (value / 2).backward()  # both ranks' losses together are the term once
    result[name] = (value.detach(), {n: p.grad.clone() for n, p in model.params.items() if p.grad is not None})
torch.save(result, sys.argv[1] + f".rank{ranks.rank}")
end_worker()
'''


def test_terms_that_read_the_model_are_the_whole_models_on_every_shard(tmp_path):
    # Mean opacity, mean scale norm and the soft count sum over both ranks' rows (model.reduce_rows): each rank's
    # value is the whole model's, and each row's gradient is the one-process gradient, whatever the shard sizes.
    from warpgs.losses import gestalt

    run_two_ranks(TERMS_WORKER, [tmp_path / "terms"], tmp_path)
    ranks = [torch.load(tmp_path / f"terms.rank{r}") for r in (0, 1)]
    for name in ("opacity", "scale", "count"):
        whole = start_model()
        value = getattr(gestalt, name)(None, {}, whole, 0)
        value.backward()
        for r in (0, 1):
            torch.testing.assert_close(ranks[r][name][0], value.detach(), msg=f"{name} on rank {r}")
        grads = {n: p.grad for n, p in whole.params.items() if p.grad is not None}
        assert grads and grads.keys() == ranks[0][name][1].keys() == ranks[1][name][1].keys(), name
        for n, g in grads.items():
            got = torch.cat([ranks[0][name][1][n], ranks[1][name][1][n]])
            assert float(g.abs().max()) > 0, (name, n)
            torch.testing.assert_close(got, g, atol=1e-9, rtol=1e-5, msg=f"{name}: d/d{n}")
