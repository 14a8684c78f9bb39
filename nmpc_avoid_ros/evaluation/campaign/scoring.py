"""Scoring of campaign runs: one closed loop -> its record; a family's records -> its summary.

Definitions (per scenario; y is the output, K the last sample; y* and y~ from reachability.py):

* at rest: the state moved less than REST_TOLERANCE (inf-norm) over the last REST_WINDOW samples.
* converged: |y - y*| < SETTLING_TOLERANCE (0.05) from some sample on, to the end (settled at y*).
* near: |y_K - y*| < NEAR_TOLERANCE (0.1) (the target itself if reachable, else y*);
  near_admissible: |y_K - y~| < NEAR_TOLERANCE.
* stop short (paper Remark 1): at rest but not converged; the distance is |y_K - y*|. Cause
  'obstacle_covers_target' if it stopped at y~ != y* (the avoidance cost moves the equilibrium);
  otherwise it stopped short of y~ too, 'no_passage' when the regions leave no admissible way from
  where it stopped to y~ (the family's passage test), else 'local_minimum'.
* penetration, clearance: core/metrics.py (keep-in expressions and regions in force per sample).
* solver failure: a sample whose solver status is not Solve_Succeeded/Solved_To_Acceptable_Level
  (budget cuts with a feasible iterate count here, as 'truncated'); fallback: a sample that applied
  the controller's fallback. Recursive feasibility: among samples k >= 1 whose predecessor's solve
  was usable (ok/truncated), the share whose own solve was usable.

Extending: a new per-run measure is one more entry in the dict of the RECORD_SECTIONS function it
belongs to (or one more function in RECORD_SECTIONS), plus a line in DEFINITIONS; a measure
derived from stored raw measures belongs in `classify` (so rebuilt summaries use the current
definition); a new summary key is one more entry in `summarize` (and in `format_summary` to print
it). Time-measured fields are listed in TIMED_FIELDS: they are the only ones that may differ
between two runs of the same scenario (see running.comparable).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...core.closed_loop import ClosedLoopRun, run_closed_loop
from ...core.controller import SOLVED, NmpcController
from ...core.errors import NmpcError
from ...core.fallback import CANDIDATES as FALLBACK_CANDIDATES
from ...core.metrics import (
    SETTLING_TOLERANCE,
    keep_in_values,
    outputs,
    penetration,
    region_values,
    settling_step,
    time_stats,
)
from ...core.models import Model
from ...core.regions import Region
from ...core.settings import ControllerSettings
from .reachability import ReachableSet
from .scenarios import Family, spec_ellipses

#: the state must move less than this (inf-norm) over the last REST_WINDOW samples to be "at rest"
REST_TOLERANCE = 5e-3
REST_WINDOW = 10
#: "ends near" a point: the final output is closer than this (output units)
NEAR_TOLERANCE = 0.1
#: a target is reachable when its projection onto Y_r moves it less than this
REACHABLE_TOLERANCE = 1e-6
#: budget of the X_N membership probe of a start whose first real solve failed
PROBE_ITERATIONS = 1000
PROBE_SOLVE_TIME = 20.0
USABLE = ("ok", "truncated")
#: one character per sample in the stored trace
STATUS_CODES = {"ok": ".", "truncated": "t", "fallback_shift": "s", "fallback_steady": "S", "fallback_safe": "X",
                "fallback_recovery": "R"}
#: the fallback candidates (core/fallback.py), as statuses
FALLBACK_KINDS = tuple(f"fallback_{kind}" for kind in FALLBACK_CANDIDATES)
#: penetration from this sample on is where the input can act (x(1) is fixed by x(0), u(0) partly)
FIRST_ACTED_SAMPLE = 2
#: record fields measured in wall time (machine- and load-dependent); ('trace', 'solve_ms') is nested
TIMED_FIELDS = ("wall_s", "solve_ms", ("trace", "solve_ms"))
#: what may end a closed loop early (a non-finite plant state refused by the controller, a failed integration)
STOPS = (NmpcError, ArithmeticError, RuntimeError, ValueError)


@dataclass
class Tools:
    """What scoring a scenario needs, built once per worker and config: the controller, Y_r, the probe."""

    controller: NmpcController
    reach: ReachableSet
    probe: NmpcController

    @classmethod
    def build(cls, settings: ControllerSettings) -> Tools:
        controller = NmpcController(settings)
        probe = NmpcController(settings.replace(mu=0.0, max_iterations=PROBE_ITERATIONS,
                                                max_solve_time=PROBE_SOLVE_TIME))
        return cls(controller, ReachableSet(settings, controller.model), probe)


@dataclass
class Scored:
    """One finished run and the reference points the record sections measure it against."""

    spec: dict[str, Any]
    family: Family
    settings: ControllerSettings
    model: Model
    run: ClosedLoopRun
    y: np.ndarray  # [K+1, p] outputs
    y_t: np.ndarray
    y_star: np.ndarray
    y_free: np.ndarray
    regions: list[Region]  # the set in force at the end
    probe: NmpcController


def start_feasibility(probe: NmpcController, x0: Sequence[float], y_t: Sequence[float]) -> str:
    """Is x0 in X_N (the NLP's feasible set)? A cold solve with mu = 0 (V_a is soft, so X_N does not
    depend on mu or y_t) and a generous budget: 'feasible', 'infeasible' or 'unknown'."""
    probe.reset()
    res = probe.step(x0, y_t, ())
    if res.status in USABLE:
        return "feasible"
    return "infeasible" if res.solver_status == "Infeasible_Problem_Detected" else "unknown"


def _vec(values: Iterable[float], digits: int = 9) -> list[float]:
    return [round(float(v), digits) for v in values]


def score_scenario(spec: dict[str, Any], family: Family, tools: Tools) -> dict[str, Any]:
    """Run one scenario's closed loop (the one driver) and score it; the record (with 'trace') is JSON-ready."""
    start = time.perf_counter()
    controller = tools.controller
    controller.reset()
    run = run_closed_loop(controller, spec["x0"], spec["target"], spec["steps"], spec["plant"],
                          regions=family.schedule(spec), stop_on=STOPS)
    if len(run.u) < 1:
        raise RuntimeError(f"closed loop stopped before two samples: {run.stopped}")
    settings, model = controller.settings, controller.model
    regions = list(run.regions[-1]) if run.regions else spec_ellipses(spec)
    y_t = np.asarray(spec["target"], float)
    y_star = tools.reach.project(y_t)
    scored = Scored(spec, family, settings, model, run, outputs(model, run.x, run.u), y_t, y_star,
                    tools.reach.best_admissible(y_t, y_star, regions), regions, tools.probe)
    record: dict[str, Any] = {"id": spec["id"], "family": spec["family"], "index": spec["index"],
                              "spec": {k: spec[k] for k in ("x0", "target", "ellipses", "steps", "plant")}}
    for section in RECORD_SECTIONS:
        record.update(section(scored))
    record["wall_s"] = time.perf_counter() - start
    return classify(record)


def outcome_section(s: Scored) -> dict[str, Any]:
    """Where the run ended relative to y_t, y* and y~, and why it stopped short."""
    run, y = s.run, s.y
    reachable = bool(np.linalg.norm(s.y_star - s.y_t) < REACHABLE_TOLERANCE)
    free_ok = bool(np.all(np.isfinite(s.y_free)))
    blocked_target = bool(not free_ok or np.linalg.norm(s.y_free - s.y_star) > REACHABLE_TOLERANCE)
    err_best = np.linalg.norm(y - s.y_star, axis=1)
    err_free = np.linalg.norm(y - s.y_free, axis=1) if free_ok else np.full(len(y), np.nan)
    motion = float(np.max(np.abs(run.x[-REST_WINDOW - 1:] - run.x[-1])))
    at_rest = motion < REST_TOLERANCE
    settle = settling_step(err_best, 0.0, SETTLING_TOLERANCE)
    stop_short = bool(at_rest and settle is None)
    cause, passage = None, None
    if stop_short:
        if blocked_target and bool(err_free[-1] < SETTLING_TOLERANCE):
            cause = "obstacle_covers_target"
        else:
            passage = bool(free_ok and s.family.passage(run.x[-1], y[-1], s.y_free, s.regions))
            cause = "local_minimum" if passage else "no_passage"
    return {
        "n_ellipses": len(s.spec["ellipses"]), "stopped_early": run.stopped,
        "reachable": reachable, "y_star": _vec(s.y_star), "y_admissible": _vec(s.y_free),
        "target_covered": blocked_target,
        "final_state": _vec(run.x[-1]), "final_y": _vec(y[-1]),
        "error_to_target": float(np.linalg.norm(y[-1] - s.y_t)),
        "error_to_best": float(err_best[-1]), "error_to_admissible": float(err_free[-1]),
        "final_motion": motion, "at_rest": bool(at_rest),
        "settling_step": settle,
        "stop_short": stop_short, "stop_short_distance": float(err_best[-1]) if stop_short else None,
        "stop_short_beyond_admissible": float(err_free[-1]) if stop_short else None, "stop_short_cause": cause,
        "passage_to_admissible": passage,
        "final_avoidance_cost": float(run.costs[-1, 1]), "final_offset_cost": float(run.costs[-1, 0]),
    }


def avoidance_section(s: Scored) -> dict[str, Any]:
    """Penetration of the keep-in set and of the regions, clearance (core/metrics.py)."""
    return penetration(s.settings, s.model, s.run.x, s.run.u, s.run.regions, s.y)


def solver_section(s: Scored) -> dict[str, Any]:
    """Solver statuses, fallbacks, feasibility of the start, recursive feasibility, solve times."""
    run = s.run
    K = len(run.u)
    usable = [st in USABLE for st in run.status]
    pairs = sum(usable[k - 1] for k in range(1, K))
    kept = sum(usable[k - 1] and usable[k] for k in range(1, K))
    fallbacks = {kind: run.status.count(kind) for kind in FALLBACK_KINDS}
    return {
        "samples": K, "ok": run.status.count("ok"), "truncated": run.status.count("truncated"),
        "solver_failures": int(sum(st not in SOLVED for st in run.solver_status)),
        "fallbacks": int(sum(fallbacks.values())), "fallback_kinds": fallbacks,
        "initial_feasible": bool(usable[0]),
        "x0_in_feasible_set": "feasible" if usable[0] else start_feasibility(s.probe, s.spec["x0"], s.y_t),
        "rf_pairs": int(pairs), "rf_kept": int(kept),
        "non_ok_examples": [{"step": k, "status": st, "solver_status": ss}
                            for k, (st, ss) in enumerate(zip(run.status, run.solver_status)) if st != "ok"][:5],
        "solve_ms": time_stats(run.solve_time * 1e3),
        "budget_exhausted": int(sum(st in ("Maximum_Iterations_Exceeded", "Maximum_WallTime_Exceeded",
                                           "Maximum_CpuTime_Exceeded") for st in run.solver_status)),
    }


def robustness_section(s: Scored) -> dict[str, Any]:
    """Penetration where the input can act and after fallbacks; local-minimum escapes.

    penetration_after_first_step: max g over x(2..K) (0 if never inside); fallback_penetration: max
    g over the `horizon` states after each fallback sample (0 without fallbacks); escapes_tried:
    samples that solved escape guesses; escapes_taken: samples whose plan came from one.
    """
    run = s.run
    keep = keep_in_values(s.settings, s.model, run.x, run.u)
    g = region_values(s.settings, run.x, s.y, run.regions)
    if keep.size:
        g = np.maximum(g, keep.max(axis=1))
    after_fallback = [float(np.max(g[k + 1:k + 1 + s.settings.horizon]))
                      for k, st in enumerate(run.status) if st.startswith("fallback")]
    return {
        "penetration_after_first_step": max(0.0, float(np.max(g[FIRST_ACTED_SAMPLE:], initial=-math.inf))),
        "fallback_penetration": max([0.0, *after_fallback]),
        "escapes_tried": sum(bool(e) for e in run.escapes),
        "escapes_taken": sum(bool(e) and not e.startswith("shifted") for e in run.escapes),
    }


def trace_section(s: Scored) -> dict[str, Any]:
    """The trajectory kept for the figures (states to 6 digits, solve times, one status code per sample)."""
    return {"trace": {"x": [_vec(r, 6) for r in s.run.x], "solve_ms": _vec(s.run.solve_time * 1e3, 3),
                      "status": "".join(STATUS_CODES.get(st, "?") for st in s.run.status)}}


#: the parts of a record, in order; each maps a scored run to some of its fields
RECORD_SECTIONS: tuple[Callable[[Scored], dict[str, Any]], ...] = (
    outcome_section, avoidance_section, solver_section, robustness_section, trace_section)


def classify(record: dict[str, Any]) -> dict[str, Any]:
    """Set the derived flags converged / near / near_target / near_admissible / stop_short from the
    record's raw measures (so that a rebuilt campaign.json always uses the current definitions)."""
    if record.get("crashed"):
        return record
    record["converged"] = record["settling_step"] is not None and not record.get("stopped_early")
    record["near"] = bool(record["error_to_best"] < NEAR_TOLERANCE)
    record["near_target"] = bool(record["error_to_target"] < NEAR_TOLERANCE)
    err = record["error_to_admissible"]
    record["near_admissible"] = bool(err is not None and err < NEAR_TOLERANCE)  # NaN/None: no admissible point
    record["stop_short"] = bool(record["at_rest"] and not record["converged"] and not record.get("stopped_early"))
    return record


def _share(flags: Sequence[bool]) -> float | None:
    return float(np.mean(flags)) if len(flags) else None


def _max(values: Sequence[float]) -> float | None:
    return float(max(values)) if values else None


def _stats(values: Sequence[float]) -> dict[str, float | None]:
    if not values:
        return {"median": None, "max": None}
    return {"median": float(np.median(values)), "max": float(np.max(values))}


def summarize(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Summary of one family's records (shares are fractions in [0, 1]; distances in output units)."""
    crashed = [r for r in records if r.get("crashed")]
    records = [r for r in records if not r.get("crashed")]
    n = len(records)
    if not n:
        return {"scenarios": 0, "crashed": len(crashed)}
    diverged = [r for r in records if r.get("stopped_early")]
    finished = [r for r in records if not r.get("stopped_early")] or records
    reach = [r for r in records if r["reachable"]]
    unreach = [r for r in records if not r["reachable"]]
    short = [r for r in records if r["stop_short"]]
    pairs = sum(r["rf_pairs"] for r in records)
    worst = max(finished, key=lambda r: r["max_penetration"])
    feasible_start = [r for r in finished if r["x0_in_feasible_set"] == "feasible"]
    causes: dict[str, int] = {}
    for r in short:
        causes[r["stop_short_cause"]] = causes.get(r["stop_short_cause"], 0) + 1
    return {
        "scenarios": n,
        "crashed": len(crashed),
        "stopped_early": len(diverged),
        "reachable_targets": len(reach),
        "with_ellipses": sum(r["n_ellipses"] > 0 for r in records),
        "target_covered_by_region": sum(r["target_covered"] for r in records),
        "share_converged": _share([r["converged"] for r in records]),
        "share_near": _share([r["near"] for r in records]),
        "share_near_target_reachable": _share([r["near"] for r in reach]),
        "share_near_best_unreachable": _share([r["near"] for r in unreach]),
        "share_near_admissible": _share([r["near_admissible"] for r in records]),
        "share_converged_no_ellipse": _share([r["converged"] for r in records if r["n_ellipses"] == 0]),
        "share_at_rest": _share([r["at_rest"] for r in records]),
        "not_at_rest": sum(not r["at_rest"] for r in records),
        "max_penetration": float(worst["max_penetration"]),
        "max_penetration_scenario": worst["id"] if worst["max_penetration"] > 0 else None,
        "max_penetration_keep_in": float(max(r["max_penetration_keep_in"] for r in finished)),
        "max_penetration_obstacles": float(max(r["max_penetration_obstacles"] for r in finished)),
        "max_penetration_scope": "runs that did not stop early",
        "runs_with_penetration_over_1e-3": sum(r["max_penetration"] > 1e-3 for r in records),
        "samples": sum(r["samples"] for r in records),
        "solver_failures": sum(r["solver_failures"] for r in records),
        "truncated": sum(r["truncated"] for r in records),
        "fallbacks": sum(r["fallbacks"] for r in records),
        "fallback_kinds": {k: sum(r["fallback_kinds"].get(k, 0) for r in records) for k in FALLBACK_KINDS},
        "penetration_after_first_step": _max([r["penetration_after_first_step"] for r in feasible_start]),
        "penetration_after_first_step_all_runs": _max([r["penetration_after_first_step"] for r in finished]),
        "runs_penetrating_after_first_step_over_1e-3": sum(r["penetration_after_first_step"] > 1e-3
                                                          for r in feasible_start),
        "fallback_penetration": _max([r["fallback_penetration"] for r in finished]),
        "escapes_tried": sum(r["escapes_tried"] for r in records),
        "escapes_taken": sum(r["escapes_taken"] for r in records),
        "runs_with_escape_taken": sum(r["escapes_taken"] > 0 for r in records),
        "solve_ms": time_stats(np.concatenate([r["trace"]["solve_ms"] for r in records]))
        if all("trace" in r for r in records) else None,
        "runs_with_fallback": sum(r["fallbacks"] > 0 for r in records),
        "runs_with_solver_failure": sum(r["solver_failures"] > 0 for r in records),
        "first_solve_failed": sum(not r["initial_feasible"] for r in records),
        "first_solve_failed_x0_feasible": sum(not r["initial_feasible"] and r["x0_in_feasible_set"] == "feasible"
                                              for r in records),
        "x0_infeasible": sum(r["x0_in_feasible_set"] == "infeasible" for r in records),
        "x0_feasibility_unknown": sum(r["x0_in_feasible_set"] == "unknown" for r in records),
        "recursive_feasibility_rate": float(sum(r["rf_kept"] for r in records) / pairs) if pairs else None,
        "recursive_feasibility_pairs": int(pairs),
        "stop_short": len(short),
        "stop_short_causes": causes,
        "stop_short_distance": _stats([r["stop_short_distance"] for r in short]),
        "stop_short_beyond_admissible": _stats([r["stop_short_beyond_admissible"] for r in short
                                                if r["stop_short_beyond_admissible"] is not None
                                                and math.isfinite(r["stop_short_beyond_admissible"])]),
        "solve_ms_max": float(max(r["solve_ms"]["max"] for r in records)),
        "solve_ms_median_of_medians": float(np.median([r["solve_ms"]["median"] for r in records])),
        "budget_exhausted": sum(r["budget_exhausted"] for r in records),
        "examples": {
            "stop_short": [r["id"] for r in short][:5],
            "stopped_early": [f"{r['id']}: {r['stopped_early']}" for r in diverged][:5],
            "crashed": [f"{r['id']}: {r['crashed']}" for r in crashed][:5],
            "not_at_rest": [r["id"] for r in records if not r["at_rest"]][:5],
            "fallback": [r["id"] for r in records if r["fallbacks"]][:5],
            "first_solve_failed": [r["id"] for r in records if not r["initial_feasible"]][:5],
            "x0_infeasible": [r["id"] for r in records if r["x0_in_feasible_set"] == "infeasible"][:5],
        },
    }


DEFINITIONS = {
    "best_reachable": "y*: projection of y_t onto Y_r = outputs of steady states in lambda*Z (IPOPT, tol 1e-12)",
    "reachable": f"|y* - y_t| < {REACHABLE_TOLERANCE:g}",
    "best_admissible": "y~: nearest point to y_t of Y_r whose steady state lies outside all regions (grid search)",
    "at_rest": f"state moved < {REST_TOLERANCE:g} (inf-norm) over the last {REST_WINDOW} samples",
    "converged": f"|y - y*| < {SETTLING_TOLERANCE:g} from some sample on, to the end",
    "near": f"|y_K - y*| < {NEAR_TOLERANCE:g} (y* = y_t for a reachable target)",
    "stop_short": "at rest but not converged; distance |y_K - y*|; cause obstacle_covers_target (stopped at y~ != y*), "
                  "no_passage (no admissible way to y~ exists) or local_minimum (one exists)",
    "penetration": "max over sampled states of g (keep-in: expression value, e.g. |x1 x2|-2; ellipse: 1 - r^2), 0 "
                   "if never inside",
    "solver_failure": "sample whose IPOPT status is not Solve_Succeeded / Solved_To_Acceptable_Level",
    "stopped_early": "the closed loop ended before its last sample (e.g. the plant state became non-finite); such "
                     "runs count as not converged and are left out of max_penetration",
    "fallback": "sample that applied the controller's fallback (shift, steady, safe input or recovery solve: the "
                "candidate predicting the least violation, core/fallback.py)",
    "penetration_after_first_step": "max over runs (x0 in X_N, not stopped early) of the largest g over x(2..K), "
                                    "where the input can act; 0 if never inside",
    "fallback_penetration": "max over runs and fallback samples k of the largest g over x(k+1..k+N)",
    "escapes": "escapes_tried: samples that solved local-minimum escape guesses (core/candidates.py); "
               "escapes_taken: samples whose plan came from one",
    "solve_ms": "solve time per sample, ms, pooled over the family's samples: median, p99, max",
    "x0_in_feasible_set": "x0 in X_N: the first solve was usable, or a cold probe solve with mu=0 and a 1000-iteration/"
                          "20 s budget succeeded ('infeasible' if IPOPT detected infeasibility, else 'unknown')",
    "recursive_feasibility_rate": "P(solve k usable | solve k-1 usable), usable = status ok or truncated",
}


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable lines of the per-family summaries."""
    lines = []
    pct = lambda v: "n/a" if v is None else f"{100 * v:.1f}%"  # noqa: E731
    for fam, s in summary.items():
        if not s.get("scenarios"):
            lines.append(f"{fam}: no scenarios")
            continue
        ss = s["stop_short_distance"]
        lines += [
            f"{fam}: {s['scenarios']} scenarios ({s['reachable_targets']} reachable targets, "
            f"{s['with_ellipses']} with ellipses, {s['target_covered_by_region']} with y* covered by a region; "
            f"stopped early {s['stopped_early']}, crashed {s['crashed']})",
            f"  converged {pct(s['share_converged'])}  near y_t/y* {pct(s['share_near'])} "
            f"(reachable {pct(s['share_near_target_reachable'])}, unreachable {pct(s['share_near_best_unreachable'])})"
            f"  near y~ {pct(s['share_near_admissible'])}  not at rest {s['not_at_rest']}",
            f"  max penetration {s['max_penetration']:.3g} (keep-in {s['max_penetration_keep_in']:.3g}, "
            f"ellipses {s['max_penetration_obstacles']:.3g}; runs > 1e-3: {s['runs_with_penetration_over_1e-3']})",
            f"  samples {s['samples']}: solver failures {s['solver_failures']} (truncated {s['truncated']}), "
            f"fallbacks {s['fallbacks']} in {s['runs_with_fallback']} runs, recursive feasibility "
            f"{pct(s['recursive_feasibility_rate'])}",
            f"  first solve failed {s['first_solve_failed']} (x0 in X_N: {s['first_solve_failed_x0_feasible']}; "
            f"x0 outside X_N {s['x0_infeasible']}, unknown {s['x0_feasibility_unknown']})",
            f"  stop short {s['stop_short']} {s['stop_short_causes']} distance median "
            f"{_fmt(ss['median'])} max {_fmt(ss['max'])}; solve max {s['solve_ms_max']:.0f} ms",
            f"  penetration after the first step {_fmt(s['penetration_after_first_step'])} (x0 in X_N; all runs "
            f"{_fmt(s['penetration_after_first_step_all_runs'])}), after fallbacks {_fmt(s['fallback_penetration'])}; "
            f"fallbacks by candidate {s['fallback_kinds']}; escapes tried {s['escapes_tried']}, taken "
            f"{s['escapes_taken']} in {s['runs_with_escape_taken']} runs",
        ]
        if s.get("solve_ms"):
            t = s["solve_ms"]
            lines.append(f"  solve ms median {t['median']:.3g}, p99 {t['p99']:.3g}, max {t['max']:.3g}")
    return "\n".join(lines)


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3g}"
