"""`campaign`: Monte Carlo evidence over random scenarios -> one JSON plus summary plots.

    python -m nmpc_avoid_ros campaign --out out/campaign [--vdp 500] [--robot 200] [--seed 0] [--jobs N]
        [--scheduler tcp://HOST:8786] [--sweep NAME=V1,V2,...]

Scenarios: scenarios.py (the families and how each draws its scenarios); what is measured and
how it is summarised: scoring.py and reachability.py; where they run and the files: running.py.

Without --scheduler, --jobs 1 runs in this process and --jobs N > 1 on an embedded Dask
LocalCluster of N single-threaded worker processes; with --scheduler ADDRESS the scenarios run on
that existing Dask cluster (`dask scheduler`, `dask worker ADDRESS --nthreads 1`; the workers need
this package installed, not the config files: the params travel with each task).

--sweep NAME=V1,V2,... runs the same scenarios once per value of a run-time setting (JSON values:
`--sweep mu=0,1e5,1e8`, `--sweep "state_weights=[1,1],[10,1]"`), each value in its own
resumable directory <out>/<NAME>=<V>/, then writes sweep.json, sweep.md and sweep.png in --out.

Results: campaign.jsonl (one line per finished scenario, with its trajectory; a rerun skips the
ids it holds), campaign.json (per-scenario records without trajectories, plus the summary),
summary.json and PNG plots, all in --out. Bad input (unknown family count, unreachable scheduler,
structural sweep parameter, corrupt resume file): one line on stderr, exit code 2, no file changed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ...core.config.settings import load_params_file
from ...core.errors import NmpcError
from ...core.loop.closed_loop import PLANTS
from .running import (
    JSON_NAME,
    JSONL_NAME,
    RunSetup,
    build_output,
    check_meta,
    read_jsonl,
    repair_tail,
    run_dask,
    run_local,
)
from .scenarios import FAMILIES, families, interleave, make_specs, settings_from_params
from .summary import format_summary
from .sweep import parse_settings, parse_sweep, sweep_dir, write_sweep


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="campaign", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="output directory (rerun with it to resume)")
    for fam in FAMILIES:
        flag = fam.key.replace("_", "-")  # --bicycle-world N; argparse gives it the dest bicycle_world
        ap.add_argument(f"--{flag}", type=int, default=fam.default_count,
                        help=f"number of {fam.title} scenarios (default {fam.default_count})")
        ap.add_argument(f"--{flag}-steps", type=int, default=fam.default_steps,
                        help=f"samples per {fam.title} run (default {fam.default_steps})")
        ap.add_argument(f"--{flag}-config", type=Path,
                        help=f"{fam.title} params file (default: the shipped {fam.config_name})")
    ap.add_argument("--seed", type=int, default=0, help="campaign seed (default 0)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                    help="local worker processes (default: all cores; 1: in this process)")
    ap.add_argument("--scheduler", help="address of an existing Dask scheduler, e.g. tcp://10.0.0.5:8786")
    ap.add_argument("--connect-timeout", type=float, default=10.0,
                    help="seconds to wait for the scheduler to answer (default 10)")
    ap.add_argument("--sweep", help="NAME=V1,V2,...: the same scenarios once per value of a run-time setting")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="change a controller setting in every family's config (repeatable; JSON values; "
                         "structural ones too, e.g. the reference path: --set 'solver=\"ipopt\"')")
    ap.add_argument("--plant", choices=PLANTS, default="euler",
                    help="euler: the prediction model (the paper's nominal setting, default); continuous: ZOH+DOP853")
    ap.add_argument("--max-solve-time", type=float,
                    help="override the configs' solver wall-time budget, s (default: keep the configs' values)")
    ap.add_argument("--stop-after", type=int, help=argparse.SUPPRESS)  # testing: run at most this many new ones
    ap.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    return ap


def _fail(message: str) -> int:
    print(f"campaign: error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    counts = {f.key: getattr(args, f.key) for f in FAMILIES}
    steps = {f.key: getattr(args, f"{f.key}_steps") for f in FAMILIES}
    if min(counts.values()) < 0 or min(args.jobs, *steps.values()) < 1:
        return _fail("the scenario counts must be >= 0, --jobs and the steps >= 1")
    started = time.perf_counter()
    try:
        fams = families({f.key: getattr(args, f"{f.key}_config") for f in FAMILIES}, steps)
        changes = parse_settings(args.set)
        params = {key: {**load_params_file(fam.config).section("controller"), **changes} for key, fam in fams.items()}
        base = {key: settings_from_params(p, args.max_solve_time) for key, p in params.items()}
        groups = [make_specs(fam, counts[key], args.seed, base[key], args.plant) for key, fam in fams.items()]
        sweep = parse_sweep(args.sweep, base) if args.sweep else None
        meta = {"seed": args.seed, "plant": args.plant, "max_solve_time": args.max_solve_time,
                # an opt-in family (default count 0) only when asked for: older campaigns' meta stays as it was
                "configs": {f.key: str(f.config) for f in fams.values() if counts[f.key] or f.default_count},
                "steps": {f.key: f.steps for f in fams.values() if counts[f.key] or f.default_count},
                **({"set": changes} if changes else {})}
        runs = ([(args.out, {}, meta)] if sweep is None else
                [(sweep_dir(args.out, sweep.name, v), {sweep.name: v}, {**meta, "sweep": {sweep.name: v}})
                 for v in sweep.values])
        done: list[dict[str, dict[str, Any]]] = []
        for out, _, run_meta in runs:
            out.mkdir(parents=True, exist_ok=True)
            check_meta(out, run_meta)
            done.append(read_jsonl(out / JSONL_NAME))
    except (NmpcError, OSError) as exc:
        return _fail(str(exc))
    specs = [s for g in groups for s in g]
    order = interleave(groups)
    tasks, targets = [], []
    for r, (_, overrides, _) in enumerate(runs):
        setup = RunSetup(params, args.max_solve_time, overrides)
        for spec in order:
            if spec["id"] not in done[r]:
                tasks.append((spec, setup))
                targets.append(r)
    if args.stop_after is not None:
        tasks, targets = tasks[: args.stop_after], targets[: args.stop_after]
    total = len(specs) * len(runs)
    jobs = min(args.jobs, max(1, len(tasks)))
    where = f"the Dask cluster at {args.scheduler}" if args.scheduler else f"{jobs} job(s)"
    print(f"campaign: {total - len(tasks)} of {total} scenarios already done, "
          f"{len(tasks)} to run on {where} -> {args.out}", flush=True)
    status = _run(args, runs, tasks, targets)
    if status:
        return status
    results = [build_output(out, specs, run_meta, plots=not args.no_plots) for out, _, run_meta in runs]
    for (out, _, _), result in zip(runs, results):
        print(format_summary(result["summary"]))
        missing = len(specs) - len(result["scenarios"])
        print(f"campaign: {len(result['scenarios'])} scenarios in {out / JSON_NAME}"
              f"{f' ({missing} still to run)' if missing else ''}")
    if sweep is not None:
        table = write_sweep(args.out, sweep, results, plots=not args.no_plots)
        print(table)
    print(f"campaign: this invocation took {time.perf_counter() - started:.0f} s")
    return 0


def _run(args: argparse.Namespace, runs: Sequence[tuple[Path, dict, dict]], tasks: list, targets: list[int]) -> int:
    """Run the tasks, appending each record to its run's JSONL as it completes; 0, or an exit code."""
    from tqdm import tqdm

    if not tasks:
        return 0
    files = []
    for out, _, _ in runs:
        repair_tail(out / JSONL_NAME)
        files.append((out / JSONL_NAME).open("a"))

    def sink(i: int, record: dict[str, Any]) -> None:
        f = files[targets[i]]
        f.write(json.dumps(record) + "\n")
        f.flush()

    bar = tqdm(total=len(tasks), desc="campaign", unit="scenario", disable=args.no_progress, dynamic_ncols=True)
    started = time.perf_counter()
    lost: list[str] = []
    try:
        if args.scheduler or args.jobs > 1:
            lost = run_dask(tasks, sink, bar, args.scheduler, min(args.jobs, len(tasks)), args.connect_timeout)
            if lost:
                print(f"campaign: the cluster gave up on {len(lost)} scenario(s) (rerun to resume): {lost[0]}",
                      file=sys.stderr)
        else:
            run_local(tasks, sink, bar)
        seconds = time.perf_counter() - started
        ran = len(tasks) - len(lost)
        print(f"campaign: ran {ran} scenarios in {seconds:.1f} s ({ran / seconds:.2f} scenarios/s, "
              f"start-up included)", flush=True)
    except KeyboardInterrupt:
        print("campaign: interrupted; rerun with the same --out to resume", file=sys.stderr)
        return 130
    except (NmpcError, OSError) as exc:  # an unreachable scheduler, a full disk: the records so far are kept
        return _fail(str(exc).replace("\n", " "))
    finally:
        bar.close()
        for f in files:
            f.close()
    return 0
