"""The truth of the live loop: the README's sequence in real time, judged by every recorded plant state.

    python -m nmpc_avoid_ros.bench.live_truth --runs 5 --json bench/live_truth.json

Each run starts recorder, plant and controller with config/van_der_pol_live.yaml in real time (plant at
20 Hz, the compiled solvers from the cache), then the README's `send` sequence: target 5, the ellipse
centred (2, -0.5) with semi-axes 0.4 x 0.2, target -3, delete it, mu 0. It reads the bag's `/state` (the
plant's own publications) for max |x1 x2|, max |x2| and the ellipse's clearance, and `analyze`'s metrics of
the same bag beside them. Half of the runs plan from the measured state (`latency_compensation: false`),
interleaved with the others, so both see the same machine. Each run also says when the commands took effect
on the plant against the instant the controller planned from (the arrivals fitted from the recorded states,
evaluation/recorded_timing.py): the timing jitter latency compensation cannot see. `--load N` runs N busy
loops beside the nodes (a loaded machine). Results: BENCHMARKS.md, 'The truth of the live loop' and
'Command timing jitter'.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..bag.analysis import RecordedRun, load_run
from ..bag.mcap_io import Bag, load_bag
from ..bag.node_parameters import recorded_setup
from ..core.config.settings import ControllerSettings, default_config_path, load_params_file
from ..evaluation.counterfactual import recorded_plant
from ..tools.processes import NodeProcess, isolated_env

LIVE = default_config_path().parent / "van_der_pol_live.yaml"
#: the README's sequence: (send arguments, seconds to let the loop run after it)
SEQUENCE = ((["target", "5"], 16.0), (["obstacle", "ellipse", "--center", "2", "-0.5", "--axes", "0.4", "0.2"], 0.0),
            (["target", "-3"], 16.0), (["delete", "1"], 0.0), (["param", "mu", "0"], 3.0))
ELLIPSE = ((2.0, -0.5), (0.4, 0.2))


def send(env: dict[str, str], args: list[str]) -> tuple[int, str]:
    proc = subprocess.run([sys.executable, "-m", "nmpc_avoid_ros", "send", *args, "--timeout", "180"], env=env,
                          capture_output=True, text=True, timeout=240, start_new_session=True)
    return proc.returncode, proc.stderr.strip()


def live_settings() -> ControllerSettings:
    """The controller settings of config/van_der_pol_live.yaml."""
    return ControllerSettings.from_params(load_params_file(LIVE).section("controller"))


def command_timing(bag: Bag, run: RecordedRun, settings: ControllerSettings) -> dict[str, Any]:
    """ms each sample's command took effect on the plant after the instant its controller planned from
    (median, p90, max over the samples; positive: later), or why the bag does not tell it."""
    choice = recorded_plant(bag, recorded_setup(bag, "/controller"), settings, None, run)
    beyond = choice.timing.beyond_prediction() * 1e3 if choice.timing is not None else np.zeros(0)
    if not beyond.size:
        return {"note": choice.timing_note}
    return {"median": float(np.median(beyond)), "p90": float(np.percentile(beyond, 90)), "max": float(beyond.max()),
            "samples": int(beyond.size)}


def busy_loops(count: int) -> list[subprocess.Popen]:
    """`count` processes spinning a core each, in their own process groups (stopped by PID)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True)
            for _ in range(count)]


def one_run(compensate: bool, domain: int, folder: Path) -> dict[str, Any]:
    """One live run of the README's sequence; what the recorded states and analyze say of it."""
    env = isolated_env(domain, folder / "log")
    bag_path = folder / "run.mcap"
    extra = [] if compensate else ["-p", "latency_compensation:=false"]
    nodes = [NodeProcess("recorder", ["--ros-args", "-p", f"output:={bag_path}"], env, folder),
             NodeProcess("plant", ["--ros-args", "--params-file", str(LIVE)], env, folder),
             NodeProcess("controller", ["--ros-args", "--params-file", str(LIVE), *extra], env, folder)]
    refused = []
    try:
        for args, wait in SEQUENCE:
            code, err = send(env, args)
            if code != 0:
                refused.append((args, code, err))
            time.sleep(wait)
    finally:
        for node in reversed(nodes):
            node.stop()
    bag = load_bag(bag_path)
    states = np.array([msg.data for _, msg in bag.topics["/state"]])
    (cx, cy), (a, b) = ELLIPSE
    ellipse_g = 1.0 - ((states[:, 0] - cx) / a) ** 2 - ((states[:, 1] - cy) / b) ** 2
    out = folder / "analysis"
    subprocess.run([sys.executable, "-m", "nmpc_avoid_ros", "analyze", str(bag_path), "--out", str(out)], env=env,
                   capture_output=True, text=True, timeout=600, check=False)
    metrics_file = out / "metrics.json"
    settings = live_settings()
    timing = command_timing(bag, load_run(bag_path, settings=settings, bag=bag), settings)
    analyzed = json.loads(metrics_file.read_text())["bags"] if metrics_file.exists() else None
    return {"latency_compensation": compensate, "states": len(states),
            "max_abs_x1x2": float(np.max(np.abs(states[:, 0] * states[:, 1]))),
            "max_abs_x2": float(np.max(np.abs(states[:, 1]))), "max_ellipse_g": float(np.max(ellipse_g)),
            "refused_sends": refused, "command_timing_ms": timing, "analyze": analyzed}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="runs per variant (with and without compensation)")
    parser.add_argument("--json", type=Path, default=Path("bench/live_truth.json"))
    parser.add_argument("--domain", type=int, default=91, help="first ROS_DOMAIN_ID (one per run)")
    parser.add_argument("--keep", type=Path, help="keep each run's bag, logs and analysis in this folder")
    parser.add_argument("--only", choices=("on", "off"), help="only the runs with (on) or without compensation")
    parser.add_argument("--load", type=int, default=0, help="busy loops run beside the nodes (a loaded machine)")
    opts = parser.parse_args(argv)
    records = []
    load = busy_loops(opts.load)
    variants = {"on": (True,), "off": (False,), None: (True, False)}[opts.only]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for i in range(opts.runs):
                for compensate in variants:
                    folder = (opts.keep or Path(tmp)) / f"run{i}_{'on' if compensate else 'off'}"
                    folder.mkdir(parents=True, exist_ok=True)
                    record = one_run(compensate, opts.domain + len(records) % 10, folder)
                    records.append({**record, "load": opts.load})
                    print(json.dumps({k: v for k, v in record.items() if k != "analyze"}), flush=True)
    finally:
        for proc in load:
            proc.kill()
            proc.wait()
    opts.json.parent.mkdir(parents=True, exist_ok=True)
    opts.json.write_text(json.dumps({"command": " ".join(["python -m nmpc_avoid_ros.bench.live_truth", *(argv or
                                                                                                        sys.argv[1:])]),
                                     "runs": records}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
