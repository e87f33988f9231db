"""benchmarks/job_pool.py and real_capture_jobs.py: processes side by side per group, results pooled by seed."""
import json
import os
import sys
import time
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import real_capture_jobs  # noqa: E402
from job_pool import Job, detach, run_jobs  # noqa: E402

# Each job appends (start, end) to a file named after its group, so overlaps can be counted afterwards.
SLEEPER = textwrap.dedent("""
    import sys, time
    t0 = time.time(); time.sleep(0.4)
    open(sys.argv[1], "a").write(f"{t0} {time.time()}\\n")
    print("done", sys.argv[2])
""")


def most_at_once(path):
    spans = [tuple(map(float, ln.split())) for ln in Path(path).read_text().splitlines()]
    return max(sum(1 for s, e in spans if s <= t < e) for t, _ in spans)


def test_at_most_at_once_per_group_and_every_job_runs(tmp_path):
    jobs = [Job(f"{g}{i}", [sys.executable, "-c", SLEEPER, str(tmp_path / f"{g}.spans"), f"{g}{i}"], group=g)
            for g in "ab" for i in range(4)]
    done = run_jobs(jobs, 2, tmp_path / "logs", summary=lambda job, log: log.strip())
    assert sorted(j.name for j in done) == sorted(j.name for j in jobs)
    assert most_at_once(tmp_path / "a.spans") == 2 and most_at_once(tmp_path / "b.spans") == 2
    assert (tmp_path / "logs" / "a3.log").read_text().strip() == "done a3"


def test_a_failing_job_stops_the_run_with_its_log(tmp_path):
    jobs = [Job("ok", [sys.executable, "-c", "import time; time.sleep(5)"]),
            Job("bad", [sys.executable, "-c", "raise SystemExit('broken input')"])]
    with pytest.raises(SystemExit, match="(?s)bad failed.*broken input"):
        run_jobs(jobs, 2, tmp_path)


def test_keep_going_reports_a_failure_and_finishes_the_others(tmp_path, capsys):
    jobs = [Job("bad", [sys.executable, "-c", "raise SystemExit('broken input')"]),
            Job("ok", [sys.executable, "-c", "import time; time.sleep(1); print('finished')"])]
    done = run_jobs(jobs, 1, tmp_path, keep_going=True)  # one slot: "ok" starts after "bad" has failed
    assert [j.name for j in done] == ["ok"] and (tmp_path / "ok.log").read_text().strip() == "finished"
    assert "bad failed (exit 1)" in capsys.readouterr().err


def test_plan_pairs_a_seed_on_one_gpu_and_spreads_seeds():
    jobs = real_capture_jobs.plan("data/beer", [1, 2, 3], [0, 1], ["--gsplat"], "t")
    assert [(j.name, j.group) for j in jobs] == [("warpgs_s1", "0"), ("gsplat_s1", "0"), ("warpgs_s2", "1"),
                                                 ("gsplat_s2", "1"), ("warpgs_s3", "0"), ("gsplat_s3", "0")]
    assert jobs[2].env == {"CUDA_VISIBLE_DEVICES": "1"}
    assert jobs[3].cmd[-6:] == ["--only", "gsplat", "--seed", "2", "--tag", "t"]


def test_a_variant_adds_one_warpgs_run_per_seed_with_its_overrides():
    args, rest, seeds, gpus = real_capture_jobs.parse(["d", "--seeds", "1,2", "--name", "t", "--variant", "c999",
                                                       "train.alpha_max=0.999", "--", "--gsplat"])
    jobs = real_capture_jobs.plan("d", seeds, gpus, rest, "t", args.variant)
    assert [j.name for j in jobs] == ["warpgs_s1", "gsplat_s1", "warpgs_c999_s1", "warpgs_s2", "gsplat_s2",
                                      "warpgs_c999_s2"]
    assert jobs[2].cmd[-7:] == ["train.alpha_max=0.999", "--only", "warpgs", "--seed", "1", "--tag", "t_c999"]


@pytest.mark.parametrize("argv,match", [
    (["d", "--name", "n", "--variant", "a-b", "x=1", "--", "--gsplat"], "--variant a-b"),
    (["d", "--name", "n", "--variant", "a", "--", "--gsplat"], "--variant a"),
    (["d", "--name", "n", "--variant", "a", "x", "--", "--gsplat"], "KEY=VALUE"),
    (["d", "--name", "n", "--", "--gsplat", "--seed", "3"], "--seed"),
    (["d", "--name", "n", "--", "--device", "cuda"], "--gsplat"),
    (["d", "--name", "n", "--gpus", "0,x", "--", "--gsplat"], "--gpus"),
    (["d", "--name", "n", "--per-gpu", "0", "--", "--gsplat"], "--per-gpu"),
])
def test_bad_arguments_are_named(argv, match):
    with pytest.raises(SystemExit, match=match):
        real_capture_jobs.parse(argv)


FAKE_CAPTURE = textwrap.dedent("""
    # Stands in for real_capture.py: writes the result file it would, with a PSNR made from the seed and system.
    import argparse, json, os
    ap = argparse.ArgumentParser()
    ap.add_argument("data"); ap.add_argument("--only"); ap.add_argument("--seed", type=int); ap.add_argument("--tag")
    ap.add_argument("--gsplat", action="store_true"); ap.add_argument("overrides", nargs="*")
    a = ap.parse_intermixed_args()
    psnr = 20.0 + a.seed + (0.5 if a.only == "warpgs" else 0.0)
    psnr += 0.25 if "train.alpha_max=0.999" in a.overrides else 0.0
    name = f"real_capture_{os.path.basename(a.data)}_cpu_gsplat_{a.only}_only_seed{a.seed}_{a.tag}.json"
    run = {"system": a.only, "points": [{"step": 7000, "psnr": psnr}]}
    json.dump({"data": a.data, "seed": a.seed, "runs": [run]}, open(os.path.join(os.environ["OUT"], name), "w"))
    print(f"{a.only} | 7000 | 1.0 | {psnr} | 0.9 | 10")
""")


def test_runs_write_their_files_and_the_seeds_are_pooled(tmp_path, monkeypatch):
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "real_capture.py").write_text(FAKE_CAPTURE)
    monkeypatch.setattr(real_capture_jobs, "HERE", tmp_path / "bin")
    monkeypatch.setenv("OUT", str(tmp_path / "elsewhere"))
    out = real_capture_jobs.main(["data/beer", "--seeds", "1,2", "--name", "t", "--out", str(tmp_path / "res"),
                                  "--", "--gsplat"])
    (row,) = out["summary"]
    assert row["seeds"] == 2 and row["delta_mean"] == pytest.approx(0.5)
    assert len(list((tmp_path / "res").glob("real_capture_beer_*_t.json"))) == 4
    assert json.loads((tmp_path / "res" / "real_capture_seeds_t.json").read_text())["summary"] == out["summary"]
    # a rerun under the same name pools the runs again, not the earlier pooled table
    assert real_capture_jobs.main(["data/beer", "--seeds", "1,2", "--name", "t", "--out", str(tmp_path / "res"),
                                   "--", "--gsplat"])["summary"] == out["summary"]


def test_a_variant_is_pooled_against_the_same_gsplat_runs(tmp_path, monkeypatch):
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "real_capture.py").write_text(FAKE_CAPTURE)
    monkeypatch.setattr(real_capture_jobs, "HERE", tmp_path / "bin")
    out = real_capture_jobs.main(["data/beer", "--seeds", "1,2", "--name", "t", "--out", str(tmp_path),
                                  "--variant", "c999", "train.alpha_max=0.999", "--", "--gsplat"])
    assert out["summary"][0]["delta_mean"] == pytest.approx(0.5)  # the pair alone
    variant = json.loads((tmp_path / "real_capture_seeds_t_c999.json").read_text())
    assert variant["summary"][0]["seeds"] == 2 and variant["summary"][0]["delta_mean"] == pytest.approx(0.75)


def test_a_detached_command_runs_in_its_own_session_and_returns_at_once(tmp_path):
    # The child reports its session id after a pause: detach must return before that, and the child must lead a
    # session of its own (a device runner ends the processes left in the command's session).
    script = "import os, time; time.sleep(0.5); print('sid', os.getsid(0), 'pid', os.getpid())"
    log = tmp_path / "wave" / "jobs.log"
    t0 = time.perf_counter()
    pid = detach([sys.executable, "-c", script], log)
    assert time.perf_counter() - t0 < 0.5
    assert (tmp_path / "wave" / "jobs.log.pid").read_text().strip() == str(pid)
    os.waitpid(pid, 0)
    words = log.read_text().split()
    assert words == ["sid", str(pid), "pid", str(pid)] and pid != os.getsid(0)


def test_detach_reruns_the_same_wave_without_the_flag(tmp_path, monkeypatch):
    started = []
    monkeypatch.setattr(real_capture_jobs, "detach", lambda cmd, log: started.append((cmd, log)) or 4321)
    out = real_capture_jobs.main(["data/beer", "--seeds", "1,2", "--detach", "--name", "t", "--out", str(tmp_path),
                                  "--", "--gsplat", "--steps", "7000"])
    ((cmd, log),) = started
    assert out == {"detached": 4321, "log": str(tmp_path / "t_jobs.log")} and log == tmp_path / "t_jobs.log"
    assert "--detach" not in cmd and cmd[cmd.index("--"):] == ["--", "--gsplat", "--steps", "7000"]
    assert real_capture_jobs.parse(cmd[2:])[0].out == str(tmp_path)


def test_a_detached_wave_refuses_to_write_into_out_which_the_next_command_empties(tmp_path, monkeypatch):
    monkeypatch.setenv("OUT", str(tmp_path))
    with pytest.raises(SystemExit, match="--detach: give --out"):
        real_capture_jobs.parse(["data/beer", "--detach", "--name", "t", "--", "--gsplat"])
