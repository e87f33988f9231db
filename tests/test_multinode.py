"""Past one machine: two torchrun agents (`--nnodes 2 --rdzv-backend c10d`), one process each, on localhost as two
nodes would run them (each process is local rank 0 of its node), gloo on the CPU. The run ends where one process
with the same global batch ends, as the single-node launch does (tests/test_distributed.py). About 30-60 s on 2
busy cores: two agents and two trainers start, then 8 small steps. docs/distributed.md has the launch lines."""
import subprocess
import sys
import time

from gloo_helpers import free_port, wait_all
from test_distributed import K, LAUNCH_TIMEOUT, _assert_close, _env, _overrides, _snapshot, scene  # noqa: F401
from warpgs.train.checkpoint import load_checkpoint
from warpgs.train.trainer import Trainer


def _agent(port: int, overrides: list) -> list:
    """One node's torchrun agent, as docs/distributed.md launches it on each host."""
    return [sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--nproc-per-node", "1",
            "--rdzv-backend", "c10d", "--rdzv-endpoint", f"127.0.0.1:{port}", "--rdzv-id", "warpgs-test",
            "--max-restarts", "0", "-m", "warpgs.cli", "train", "default", "--quiet", *overrides]


def test_two_nodes_match_one_process(scene, tmp_path):
    two = tmp_path / "two"
    cmd = _agent(free_port(), _overrides(scene, two, K))
    agents = []
    for node in range(2):
        agents.append(subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
        time.sleep(0.5 * (node == 0))  # the first agent hosts the rendezvous store; the second joins it
    for node, (code, _, err) in enumerate(wait_all(agents, time.monotonic() + LAUNCH_TIMEOUT)):
        assert code == 0, f"agent {node}: {err[-3000:]}"

    one = Trainer(None, overrides=_overrides(scene, tmp_path / "one", K), quiet=True)
    for _ in range(K):
        one.train_step()
    saved = load_checkpoint(two / "checkpoint.pt")
    assert saved["step"] == K and saved["model"]["params"]["means"].shape[0] > 400  # through two refines
    got = {f"param.{n}": t for n, t in saved["model"]["params"].items()}
    got.update({f"param.modules.{n}": t for n, t in saved["modules"].items()})
    got.update({f"strategy.{k}": saved["strategy"][k] for k in ("grad_accum", "count", "max_radii")})
    _assert_close(got, _snapshot(one), "two nodes vs one process at step 8")
