"""Campaigns on a real Dask cluster on loopback: a `dask scheduler` and two `dask worker` processes,
each in its own process group, started and stopped by PID.

Records are compared with `running.comparable` (every field but the wall-time measured ones);
a non-binding wall-time budget (--max-solve-time 30) makes the outcome independent of load.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

import pytest

from nmpc_avoid_ros.evaluation.campaign.cli import main
from nmpc_avoid_ros.evaluation.campaign.running import JSONL_NAME, comparable, read_jsonl
from nmpc_avoid_ros.tools.processes import NodeProcess

pytestmark = pytest.mark.slow

DASK = [str(Path(sys.executable).parent / "dask")]
# 40 scenarios: 30 van der Pol and 10 robot runs, short, so that the whole module stays near a minute
ARGS = ["--vdp", "30", "--robot", "10", "--seed", "11", "--vdp-steps", "15", "--robot-steps", "10",
        "--max-solve-time", "30", "--no-plots", "--no-progress"]
SCENARIOS = 40


def _wait(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.1)


def _workers(address: str) -> dict:
    from distributed import Client

    with Client(address, timeout=10) as client:
        return client.scheduler_info()["workers"]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """(scheduler address, {name: worker process}) of a scheduler on a free loopback port and two workers."""
    logs = tmp_path_factory.mktemp("dask")
    env = dict(os.environ)
    address_file = logs / "scheduler.json"
    procs = [NodeProcess("scheduler", ["--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                       "--scheduler-file", str(address_file)], env, logs, program=DASK)]
    workers: dict[str, NodeProcess] = {}
    try:
        _wait(address_file.exists, 30, "the scheduler's address file")
        _wait(lambda: "address" in json.loads(address_file.read_text() or "{}"), 10, "the scheduler's address")
        address = json.loads(address_file.read_text())["address"]
        for name in ("w1", "w2"):
            workers[name] = NodeProcess("worker", [address, "--name", name, "--nthreads", "1", "--no-nanny",
                                                   "--no-dashboard", "--host", "127.0.0.1"], env, logs, program=DASK)
            procs.append(workers[name])
        _wait(lambda: len(_workers(address)) == 2, 60, "two workers")
        yield address, workers
    finally:
        for proc in reversed(procs):
            proc.stop(signal.SIGTERM, timeout=10)


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    """The same campaign in this process (--jobs 1): records by id."""
    out = tmp_path_factory.mktemp("local")
    assert main(["--out", str(out), "--jobs", "1", *ARGS]) == 0
    records = read_jsonl(out / JSONL_NAME)
    assert len(records) == SCENARIOS
    return records


def test_cluster_records_equal_the_local_ones(cluster, local, tmp_path):
    address, _ = cluster
    assert main(["--out", str(tmp_path), "--scheduler", address, *ARGS]) == 0
    remote = read_jsonl(tmp_path / JSONL_NAME)
    assert sorted(remote) == sorted(local)
    assert not any(r.get("crashed") for r in remote.values())
    assert {k: comparable(r) for k, r in remote.items()} == {k: comparable(r) for k, r in local.items()}


def test_a_worker_killed_mid_run_loses_nothing(cluster, local, tmp_path):
    address, workers = cluster
    run = NodeProcess("campaign", ["--out", str(tmp_path), "--scheduler", address, *ARGS], dict(os.environ),
                      tmp_path / "logs")
    try:
        jsonl = tmp_path / JSONL_NAME
        _wait(lambda: jsonl.exists() and len(jsonl.read_text().splitlines()) >= 4 or not run.alive(), 120,
              "the first records")
        done_at_kill = len(jsonl.read_text().splitlines())
        victim = workers["w1"]
        os.kill(victim.pid, signal.SIGKILL)
        victim.proc.wait(10)
        assert run.proc.wait(180) == 0, run.output()
    finally:
        run.stop(signal.SIGINT)
    assert done_at_kill < SCENARIOS  # the kill came while scenarios were still to run
    assert [w["name"] for w in _workers(address).values()] == ["w2"]
    lines = jsonl.read_text().splitlines()
    records = read_jsonl(jsonl)
    assert len(lines) == len(records) == SCENARIOS  # every scenario once, none lost, none twice
    assert {k: comparable(r) for k, r in records.items()} == {k: comparable(r) for k, r in local.items()}
