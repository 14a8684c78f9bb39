"""Where campaign scenarios run, and the files that make a campaign resumable.

A scenario runs through `run_scenario(spec, setup)`: a pure function of its arguments (the spec
and a RunSetup holding the controller params themselves, not file names), so it gives the same
record in this process, in a pool worker or on any Dask worker, in any order; a worker builds
each configuration's controller, reachable set and probe once and reuses them (reset per
scenario). Records differ only in TIMED_FIELDS (scoring.py); `comparable` strips those.

Results: campaign.jsonl holds one line per finished scenario, appended and flushed as each one
completes (a rerun skips the ids it holds; a torn last line from a kill is cut); campaign.json
and summary.json are rebuilt from it; campaign_meta.json pins what the directory holds.
"""

from __future__ import annotations

import json
import math
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...core.errors import ConfigError
from .scenarios import families, settings_from_params
from .scoring import TIMED_FIELDS, Tools, classify, score_scenario
from .summary import DEFINITIONS, summarize

JSONL_NAME = "campaign.jsonl"
JSON_NAME = "campaign.json"
META_NAME = "campaign_meta.json"


@dataclass(frozen=True)
class RunSetup:
    """Everything a worker needs besides the spec: each family's controller params (the params
    file's `controller` section), the wall-time budget override (s) and run-time setting overrides."""

    params: Mapping[str, Mapping[str, Any]]
    max_solve_time: float | None = None
    overrides: Mapping[str, Any] = field(default_factory=dict)

    def key(self, family: str) -> str:
        return json.dumps([family, self.params[family], self.max_solve_time, dict(self.overrides)], sort_keys=True)


#: per worker process: (setup key, thread) -> Tools
_TOOLS: dict[tuple[str, int], Tools] = {}


def tools_for(family: str, setup: RunSetup) -> Tools:
    """The family's Tools under `setup`, built once per worker thread (controllers are not shared)."""
    key = (setup.key(family), threading.get_ident())
    if key not in _TOOLS:
        settings = settings_from_params(setup.params[family], setup.max_solve_time, setup.overrides)
        _TOOLS[key] = Tools.build(settings)
    return _TOOLS[key]


def run_scenario(spec: dict[str, Any], setup: RunSetup) -> dict[str, Any]:
    """Run and score one scenario. Never raises: an unexpected error gives a record with 'crashed'."""
    try:
        family = families()[spec["family"]]
        return (family.score or score_scenario)(spec, family, tools_for(spec["family"], setup))
    except Exception as exc:  # noqa: BLE001 - one bad scenario must not end the campaign
        return {"id": spec["id"], "family": spec["family"], "index": spec["index"],
                "spec": {k: spec[k] for k in ("x0", "target", "ellipses", "steps", "plant")},
                "crashed": f"{type(exc).__name__}: {exc}"}


def comparable(record: Mapping[str, Any]) -> dict[str, Any]:
    """The record without its wall-time measured fields: equal for the same scenario wherever it ran."""
    out = json.loads(json.dumps(record))
    for name in TIMED_FIELDS:
        if isinstance(name, tuple):
            out.get(name[0], {}).pop(name[1], None)
        else:
            out.pop(name, None)
    return out


class CampaignFileError(ConfigError):
    """A campaign file that cannot be read as written (the file is left untouched)."""


class SchedulerUnreachable(ConfigError):
    """The Dask scheduler given did not answer in time."""


def read_jsonl(path: Path) -> dict[str, dict[str, Any]]:
    """Finished records by id; a torn last line (a write cut by a kill) is ignored, any other
    unreadable line raises CampaignFileError (the file may not be appended to blindly)."""
    done: dict[str, dict[str, Any]] = {}
    if not path.exists():
        return done
    data = path.read_bytes()
    lines = data.split(b"\n")
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError):
            if number == len(lines):  # no newline after it: a torn write, repaired before appending
                continue
            raise CampaignFileError(f"{path}:{number} is not a JSON record; move the file away or fix "
                                    f"that line to resume") from None
        if not isinstance(rec, dict) or not isinstance(rec.get("id"), str):
            raise CampaignFileError(f"{path}:{number} is not a scenario record (a JSON object with an 'id')")
        done[rec["id"]] = rec
    return done


def repair_tail(path: Path) -> None:
    """Cut a torn last line so that appended records start on a line of their own."""
    if not path.exists():
        return
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        path.write_bytes(data[: data.rfind(b"\n") + 1])


def check_meta(out: Path, meta: dict[str, Any]) -> None:
    """Pin what `out` holds: refuse a directory that holds a campaign with other meta values."""
    path = out / META_NAME
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            raise CampaignFileError(f"{path} is not JSON; move it away to resume") from None
        # `set` is written only when given (older campaigns' meta stays as it was), so its absence counts too
        keys = set(meta) | ({"set"} & set(old) if isinstance(old, dict) else set())
        diff = sorted(k for k in keys if not isinstance(old, dict) or old.get(k) != meta.get(k))
        if diff:
            raise ConfigError(f"{out} holds a campaign with other {', '.join(diff)} "
                              f"({', '.join(f'{k}={old.get(k)!r}' for k in diff) if isinstance(old, dict) else old});"
                              f" use another --out")
    else:
        path.write_text(json.dumps(meta, indent=2))


#: a finished scenario's record goes to sink(task index, record)
Sink = Callable[[int, dict[str, Any]], None]


def run_local(tasks: Sequence[tuple[dict[str, Any], RunSetup]], sink: Sink, bar: Any) -> None:
    """Every task in this process, in order."""
    for i, (spec, setup) in enumerate(tasks):
        sink(i, run_scenario(spec, setup))
        bar.update()


def run_dask(tasks: Sequence[tuple[dict[str, Any], RunSetup]], sink: Sink, bar: Any, scheduler: str | None,
             jobs: int, connect_timeout: float = 10.0) -> list[str]:
    """The tasks on a Dask cluster: the one at `scheduler` (an address), else an embedded LocalCluster
    of `jobs` single-threaded worker processes. Records are sunk as they complete; a worker that
    dies takes its running tasks with it and the scheduler reruns them elsewhere. Returns the ids
    of the tasks the cluster gave up on (e.g. every worker that ran them died)."""
    from dask.base import tokenize
    from distributed import Client, LocalCluster, as_completed

    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout=connect_timeout)
        except (OSError, TimeoutError) as exc:
            reason = str(exc).replace("\n", " ")
            raise SchedulerUnreachable(f"cannot reach the Dask scheduler at {scheduler}: {reason}") from None
        if not client.scheduler_info().get("workers"):
            print(f"campaign: no worker at {scheduler} yet; waiting for one (`dask worker {scheduler}`)",
                  file=sys.stderr, flush=True)
    else:
        cluster = LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)
    lost: list[str] = []
    try:
        keys = [f"{spec['id']}-{tokenize(spec, setup)}" for spec, setup in tasks]
        futures = [client.submit(run_scenario, spec, setup, key=key, pure=True)
                   for key, (spec, setup) in zip(keys, tasks)]
        index = {fut.key: i for i, fut in enumerate(futures)}
        for fut in as_completed(futures):
            i = index[fut.key]
            if fut.status == "finished":
                sink(i, fut.result())
            else:
                lost.append(f"{tasks[i][0]['id']}: {fut.exception()!r}")
            bar.update()
            fut.release()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return lost


def build_output(out: Path, specs: Sequence[dict[str, Any]], meta: dict[str, Any], plots: bool = True
                 ) -> dict[str, Any]:
    """campaign.json (records without traces, summary per family) and plots, from the JSONL."""
    done = read_jsonl(out / JSONL_NAME)
    own = {f.key for f in families().values() if f.summarize is not None}  # families scored their own way
    records = [done[s["id"]] if s["family"] in own else classify(done[s["id"]]) for s in specs if s["id"] in done]
    plotted = [r for r in records if not r.get("crashed") and r["family"] not in own]
    summary = {fam: (families()[fam].summarize or summarize)([r for r in records if r["family"] == fam])
               for fam in dict.fromkeys(s["family"] for s in specs)}
    result = {"meta": meta, "definitions": DEFINITIONS, "summary": summary,
              "scenarios": [{k: v for k, v in r.items() if k != "trace"} for r in records]}
    (out / JSON_NAME).write_text(json.dumps(strict_json(result), indent=1, allow_nan=False))
    head = {"meta": meta, "definitions": DEFINITIONS, "summary": summary}
    (out / "summary.json").write_text(json.dumps(strict_json(head), indent=2, allow_nan=False))
    if plots and plotted:
        from .plots import write_plots

        write_plots(out, plotted, {s["family"]: s["config"] for s in specs})
    return result


def strict_json(value: Any) -> Any:
    """The value with NaN/inf floats replaced by None (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, list):
        return [strict_json(v) for v in value]
    return value
