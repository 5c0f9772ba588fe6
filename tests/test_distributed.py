"""Evaluations across processes (`boxjax.experiments.distributed`, `boxjax evaluate --coordinator`): the
shares, the settings' checks, and two processes on this machine giving the rows of one."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

import numpy as np
import pytest

from boxjax.cli import main
from boxjax.experiments import distributed


@pytest.mark.parametrize(("n", "count"), [(1, 1), (7, 2), (10, 3), (2, 4)])
def test_the_shares_run_every_box_once(n, count):
    shares = [distributed.share(n, i, count) for i in range(count)]
    assert sorted(j for s in shares for j in s) == list(range(n))
    assert max(map(len, shares)) - min(map(len, shares)) <= 1  # balanced (a share may be empty)
    assert distributed.share(n) == list(range(n))  # one process: every box
    assert distributed.gather({"rows": [1]}) == [{"rows": [1]}]  # one process: its own results


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["--coordinator", "localhost:12355", "--num-processes", "2"], "go together"),
        (["--coordinator", "localhost", "--num-processes", "2", "--process-id", "0"], "HOST:PORT"),
        (["--coordinator", "localhost:12355", "--num-processes", "2", "--process-id", "2"], "--process-id"),
        (
            ["--coordinator", "localhost:12355", "--num-processes", "0", "--process-id", "0"],
            "--num-processes",
        ),
        (["--num-processes", "2"], "--coordinator"),
    ],
)
def test_bad_distributed_settings_exit_2_naming_them(argv, named, capsys):
    assert main(["evaluate", "--boxes", "2", *argv]) == 2
    assert named in capsys.readouterr().err


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _run_two(cmd: list[str], out) -> list[str]:
    """`cmd` in two processes with a localhost coordinator, process 0 writing to `out`; their stdouts."""
    port = _free_port()
    procs = [
        subprocess.Popen(
            [*cmd, "--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id", str(i)]
            + (["--out", str(out)] if i == 0 else []),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-2000:]
    return [o for o, _ in outs]


def test_two_processes_give_the_rows_of_one(tmp_path):
    """Two processes with a localhost coordinator, each running its share of 3 boxes (one hazardous) one at
    a time, and process 0 writing them all: the same rows, balance traces and actions as one process on
    the same boxes (episodes cut at 60 control steps: the exploration and the first turning steps)."""
    cfg = tmp_path / "short.toml"
    cfg.write_text("[task]\nmax_steps = 60\n")
    args = [
        "evaluate",
        "--boxes",
        "2",
        "--hazardous",
        "1",
        "--one-at-a-time",
        "--gradient-steps",  # the planner without its gradient refinement compiles in a fraction of
        "0",  # the default's time; what is tested here is the processes' shares and their gathering
        "--config",
        str(cfg),
        "--quiet",
    ]
    cmd = [sys.executable, "-m", "boxjax", *args, "--json"]
    # one process first: it fills the session's compilation cache, which the two then read
    one = subprocess.run([*cmd, "--out", str(tmp_path / "one")], capture_output=True, text=True, timeout=300)
    assert one.returncode == 0, one.stderr[-2000:]
    outs = _run_two(cmd, tmp_path / "two")
    worker = json.loads(outs[1].strip().splitlines()[-1])
    assert worker["process_id"] == 1 and worker["processes"] == 2 and "files" not in worker

    def rows(d):
        doc = json.loads((tmp_path / d / "evaluation.json").read_text())
        return [{k: v for k, v in r.items() if k not in ("wall_s", "plan_ms_median")} for r in doc["rows"]]

    assert rows("two") == rows("one") and len(rows("one")) == 3
    assert {r["outcome"] for r in rows("one")} - {"step_cap", "aborted"} == set()  # cut short, no failure
    with np.load(tmp_path / "two" / "boxes.npz") as a, np.load(tmp_path / "one" / "boxes.npz") as b:
        for k in ("balance", "actions", "keys"):
            np.testing.assert_array_equal(a[k], b[k])


@pytest.mark.slow
def test_two_processes_run_the_batched_learned_path(tmp_path):
    """The default path across two processes (batched, host devices per process, the learned estimator):
    every box gets an outcome, in box order, with its own key. Batched, the rows agree with one
    process's in distribution, not bit for bit (the module docstring)."""
    cfg = tmp_path / "short.toml"
    cfg.write_text("[task]\nmax_steps = 60\n")
    base = [sys.executable, "-m", "boxjax", "evaluate", "--boxes", "3", "--hazardous", "2", "--estimator"]
    base += ["learned", "--config", str(cfg), "--quiet", "--json"]
    _run_two(base, tmp_path / "two")
    doc = json.loads((tmp_path / "two" / "evaluation.json").read_text())
    assert [r["index"] for r in doc["rows"]] == list(range(5)) and doc["summary"]["processes"] == 2
    assert all(r["outcome"] for r in doc["rows"]) and sum(r["hazardous"] for r in doc["rows"]) == 2
