"""A campaign family's summary (scoring.py gives the records), its definitions, and its text form.

A new summary key is one more entry in `summarize` (plus a line in `format_summary` to print
it and, to compare it across values, an entry in sweep.SWEEP_KEYS); a definition a reader of
campaign.json needs is one more entry in DEFINITIONS.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ...core.loop.metrics import SETTLING_TOLERANCE, time_stats
from .scoring import FALLBACK_KINDS, NEAR_TOLERANCE, REACHABLE_TOLERANCE, REST_TOLERANCE, REST_WINDOW


def _share(flags: Sequence[bool]) -> float | None:
    return float(np.mean(flags)) if len(flags) else None


def _max(values: Sequence[float]) -> float | None:
    return float(max(values)) if values else None


def _min(values: Sequence[float]) -> float | None:
    return float(min(values)) if values else None


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
    # each run's state-to-command times [K] (absent from campaigns scored before they were recorded)
    commands = [r["trace"]["command_ms"] for r in records] if all(
        "command_ms" in r.get("trace", {}) for r in records) else None
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
        "runs_with_obstacle_penetration_over_1e-3": sum(r["max_penetration_obstacles"] > 1e-3 for r in records),
        "collision_rate": _share([r["max_penetration_obstacles"] > 1e-3 for r in records]),
        "min_clearance_obstacles": _min([r["min_clearance_obstacles"] for r in finished
                                         if r.get("min_clearance_obstacles") is not None]),
        "min_clearance_obstacles_median": _stats([r["min_clearance_obstacles"] for r in finished
                                                  if r.get("min_clearance_obstacles") is not None])["median"],
        "runs_with_penetration_over_1e-3": sum(r["max_penetration"] > 1e-3 for r in records),
        "samples": sum(r["samples"] for r in records),
        "solver_failures": sum(r["solver_failures"] for r in records),
        "truncated": sum(r["truncated"] for r in records),
        "unconverged": sum(r.get("unconverged", 0) for r in records),  # records from before the status: none
        "fallbacks": sum(r["fallbacks"] for r in records),
        "fallbacks_far": sum(r.get("fallbacks_far", 0) for r in records),
        "fallback_kinds": {k: sum(r["fallback_kinds"].get(k, 0) for r in records) for k in FALLBACK_KINDS},
        "penetration_after_first_step": _max([r["penetration_after_first_step"] for r in feasible_start]),
        "penetration_after_first_step_all_runs": _max([r["penetration_after_first_step"] for r in finished]),
        "runs_penetrating_after_first_step_over_1e-3": sum(r["penetration_after_first_step"] > 1e-3
                                                          for r in feasible_start),
        "runs_unavoidable_at_start": sum(r.get("unavoidable_at_start", False) for r in feasible_start),
        "penetration_after_first_step_avoidable_start": _max([r["penetration_after_first_step"] for r in feasible_start
                                                             if not r.get("unavoidable_at_start", False)]),
        # between the samples too (core/loop/intersample.py; absent from campaigns scored before it)
        "penetration_after_first_step_between_avoidable_start": _max([
            r["penetration_after_first_step_between"] for r in feasible_start
            if not r.get("unavoidable_at_start", False) and "penetration_after_first_step_between" in r]),
        "fallback_penetration": _max([r["fallback_penetration"] for r in finished]),
        "fallback_penetration_avoidable_start": _max([r["fallback_penetration"] for r in feasible_start
                                                     if not r.get("unavoidable_at_start", False)]),
        "escapes_tried": sum(r["escapes_tried"] for r in records),
        "escapes_taken": sum(r["escapes_taken"] for r in records),
        "runs_with_escape_taken": sum(r["escapes_taken"] > 0 for r in records),
        "passages": sum(r.get("passages", 0) for r in records),
        "passage_samples": sum(r.get("passage_samples", 0) for r in records),
        "runs_with_passage": sum(r.get("passages", 0) > 0 for r in records),
        "starts_cut_by_time": sum(r.get("starts_cut_by_time", 0) for r in records),
        "runs_with_starts_cut_by_time": sum(r.get("starts_cut_by_time", 0) > 0 for r in records),
        "solve_ms": time_stats(np.concatenate([r["trace"]["solve_ms"] for r in records]))
        if all("trace" in r for r in records) else None,
        # the state-to-command part, pooled over all samples and over those after each run's first (warm)
        "command_ms": time_stats(np.concatenate(commands)) if commands else None,
        "command_ms_warm": time_stats(np.concatenate([c[1:] for c in commands])) if commands else None,
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
        # no passage although the corridor test alone finds one (van der Pol: the dynamics cannot travel it)
        "no_passage_corridor_open": sum(r["stop_short_cause"] == "no_passage" and bool(r.get("corridor_to_admissible"))
                                        for r in short),
        "stop_short_distance": _stats([r["stop_short_distance"] for r in short]),
        "stop_short_beyond_admissible": _stats([r["stop_short_beyond_admissible"] for r in short
                                                if r["stop_short_beyond_admissible"] is not None
                                                and math.isfinite(r["stop_short_beyond_admissible"])]),
        "solve_ms_max": float(max(r["solve_ms"]["max"] for r in records)),
        "solve_ms_median_of_medians": float(np.median([r["solve_ms"]["median"] for r in records])),
        "budget_exhausted": sum(r["budget_exhausted"] for r in records),
        **certificate_summary(records),
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


def certificate_summary(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Certificate violation rates (violations per checked sample), pooled, nominal and mismatched samples."""
    def rate(violations: int, checked: int) -> float | None:
        return violations / checked if checked else None

    total = [sum(r.get(k, 0) for r in records) for k in ("certificate_violations", "certificate_checked",
                                                          "certificate_violations_nominal",
                                                          "certificate_checked_nominal")]
    mismatch = [r["model_mismatch_max"] for r in records if r.get("model_mismatch_max") is not None]
    return {"certificate_checked": total[1], "certificate_violations": total[0],
            "certificate_violation_rate": rate(total[0], total[1]),
            "certificate_violation_rate_nominal": rate(total[2], total[3]),
            "certificate_violation_rate_mismatched": rate(total[0] - total[2], total[1] - total[3]),
            "runs_with_certificate_violation": sum(r.get("certificate_violations", 0) > 0 for r in records),
            "model_mismatch_max": _max(mismatch)}


DEFINITIONS = {
    "best_reachable": "y*: projection of y_t onto Y_r = outputs of steady states in lambda*Z (IPOPT, tol 1e-12)",
    "reachable": f"|y* - y_t| < {REACHABLE_TOLERANCE:g}",
    "best_admissible": "y~: nearest point to y_t of Y_r whose steady state lies outside all regions (grid search)",
    "at_rest": f"state moved < {REST_TOLERANCE:g} (inf-norm) over the last {REST_WINDOW} samples",
    "converged": f"|y - y*| < {SETTLING_TOLERANCE:g} from some sample on, to the end",
    "near": f"|y_K - y*| < {NEAR_TOLERANCE:g} (y* = y_t for a reachable target)",
    "stop_short": "at rest but not converged; distance |y_K - y*|; cause obstacle_covers_target (stopped at y~ != y*), "
                  "at_margin (stopped at y~ among the regions as planned, inflated by planning_margin: their margin "
                  "holds it off y~; a local_minimum before 2026-12-05), "
                  "no_passage (no admissible way to y~ exists) or local_minimum (one exists); van der Pol's way is a "
                  "clear trajectory of the model through a corridor of free x2 (corridor_to_admissible: the corridor "
                  "alone, the test before 2026-12-05)",
    "penetration": "max over sampled states of g (keep-in: expression value, e.g. |x1 x2|-2; ellipse: 1 - r^2), 0 "
                   "if never inside; a moving ellipse is taken where it is at each sample's time",
    "collision_rate": "share of runs whose penetration into an obstacle (keep-in expressions left out) exceeds 1e-3",
    "min_clearance_obstacles": "min over runs (not stopped early) of -max g over the obstacles alone; "
                               "_median: the median over runs",
    "solver_failure": "sample whose IPOPT status is not Solve_Succeeded / Solved_To_Acceptable_Level",
    "stopped_early": "the closed loop ended before its last sample (e.g. the plant state became non-finite); such "
                     "runs count as not converged and are left out of max_penetration",
    "fallback": "sample that applied the controller's fallback (shift, steady, safe input or recovery solve: the "
                "candidate predicting the least violation, core/sample/fallback.py)",
    "penetration_after_first_step": "max over runs (x0 in X_N, not stopped early) of the largest g over x(2..K), "
                                    "where the input can act; 0 if never inside",
    "fallbacks_far": "fallback samples with no region within 1 (m for the robots; the state plane's units for van der "
                     "Pol) of the state: a fallback with no obstacle near",
    "fallback_penetration": "max over runs and fallback samples k of the largest g over x(k+1..k+N)",
    "unavoidable_at_start": "x0 in X_N, but the least-violating input of sample 0 (plan, safe input or recovery "
                            "solve) still predicts a violation over 1e-3: a region cannot be avoided from x0 "
                            "(X_N has the hard constraints only); penetration_after_first_step_avoidable_start "
                            "and fallback_penetration_avoidable_start leave these runs (and x0 outside X_N) out",
    "escapes": "escapes_tried: samples that solved local-minimum escape guesses (core/sample/candidates.py); "
               "escapes_taken: samples whose plan came from one; passages: entries into the passage mode "
               "(core/sample/passage.py, the longer escape_horizon), passage_samples: samples spent in it",
    "starts_cut_by_time": "solver starts the sample's deadline stopped or its spent budget skipped (core/nlp/search.py "
                          "SearchReport.cut_by_time), and the runs with any: their outcomes may depend on the "
                          "machine's load (a scene that converges alone can fail beside a second job)",
    "solve_ms": "solve time per sample, ms, pooled over the family's samples: median, p99, max (all solver time of "
                "a sample: before its command and its preparation between the samples)",
    "command_ms": "state to command per sample, ms, pooled: the solver time before the command (a prepared plan's "
                  "answer or the search); _warm without each run's first sample",
    "x0_in_feasible_set": "x0 in X_N: the first solve was usable, or a cold probe solve with mu=0 and a 1000-iteration/"
                          "20 s budget succeeded ('infeasible' if IPOPT detected infeasibility, else 'unknown')",
    "recursive_feasibility_rate": "P(solve k usable | solve k-1 usable), usable = status ok or truncated",
    "certificate_violation_rate": "violations of the value-function decrease (docs/certificate.md) per checked "
                                  "sample, pooled; _nominal: among samples whose measured state is within 1e-6 of "
                                  "the previous plan's x(1) (the proof's nominal model), _mismatched: the others",
    "model_mismatch_max": "largest |x(k) - x_pred(k)| (inf-norm) between a measured state and the previous plan's "
                          "x(1): 0 up to rounding on the Euler plant, the one-step model error on the continuous one",
}


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable lines of the per-family summaries."""
    lines = []
    pct = lambda v: "n/a" if v is None else f"{100 * v:.1f}%"  # noqa: E731
    for fam, s in summary.items():
        if not s.get("scenarios"):
            lines.append(f"{fam}: no scenarios")
            continue
        if "reached" in s:  # the world family (world.py)
            lines.append(f"{fam}: {s['scenarios']} scenarios (crashed {s['crashed']}): reached {pct(s['reached'])}, "
                         f"collisions {pct(s['collisions'])}, least body clearance {s['min_body_clearance_m']:.3f} m, "
                         f"perception median {s['perception_ms_median']:.2f} ms (max {s['perception_ms_max']:.1f}), "
                         f"solve median {s['solve_ms_median']:.1f} ms (max {s['solve_ms_max']:.0f}), fallback "
                         f"samples {s['fallback_samples']}")
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
            f"  samples {s['samples']}: solver failures {s['solver_failures']} (truncated {s['truncated']}, "
            f"unconverged {s['unconverged']}), "
            f"fallbacks {s['fallbacks']} in {s['runs_with_fallback']} runs "
            f"({s['fallbacks_far']} with no region within 1), "
            f"recursive feasibility {pct(s['recursive_feasibility_rate'])}",
            f"  first solve failed {s['first_solve_failed']} (x0 in X_N: {s['first_solve_failed_x0_feasible']}; "
            f"x0 outside X_N {s['x0_infeasible']}, unknown {s['x0_feasibility_unknown']})",
            f"  stop short {s['stop_short']} {s['stop_short_causes']} (no passage with an open corridor "
            f"{s['no_passage_corridor_open']}) distance median "
            f"{_fmt(ss['median'])} max {_fmt(ss['max'])}; solve max {s['solve_ms_max']:.0f} ms",
            f"  penetration after the first step {_fmt(s['penetration_after_first_step'])} (x0 in X_N; all runs "
            f"{_fmt(s['penetration_after_first_step_all_runs'])}; regions avoidable from x0 "
            f"{_fmt(s['penetration_after_first_step_avoidable_start'])}, unavoidable in "
            f"{s['runs_unavoidable_at_start']} runs), after fallbacks {_fmt(s['fallback_penetration'])} "
            f"(avoidable start {_fmt(s['fallback_penetration_avoidable_start'])})",
            f"  fallbacks by candidate {_kinds(s['fallback_kinds'])}; escapes tried {s['escapes_tried']}, taken "
            f"{s['escapes_taken']} in {s['runs_with_escape_taken']} runs; passages {s.get('passages', 0)} in "
            f"{s.get('runs_with_passage', 0)} runs ({s.get('passage_samples', 0)} samples); starts cut by the "
            f"clock {s.get('starts_cut_by_time', 0)} in {s.get('runs_with_starts_cut_by_time', 0)} runs",
        ]
        if s.get("certificate_checked"):
            lines.append(f"  certificate violations {s['certificate_violations']} of {s['certificate_checked']} "
                         f"checked samples ({pct(s['certificate_violation_rate'])}; nominal "
                         f"{pct(s['certificate_violation_rate_nominal'])}, mismatched "
                         f"{pct(s['certificate_violation_rate_mismatched'])}) in "
                         f"{s['runs_with_certificate_violation']} runs; model mismatch max "
                         f"{_fmt(s['model_mismatch_max'])}")
        if s.get("solve_ms"):
            t = s["solve_ms"]
            lines.append(f"  solve ms median {t['median']:.3g}, p99 {t['p99']:.3g}, max {t['max']:.3g}")
        if s.get("command_ms_warm"):
            t = s["command_ms_warm"]
            lines.append(f"  state to command ms after the first sample: median {t['median']:.3g}, p99 "
                         f"{t['p99']:.3g}, max {t['max']:.3g}")
    return "\n".join(lines)


def _kinds(counts: dict) -> str:
    """'shift 0, steady 0, safe 2, recovery 90' from fallback counts keyed by StepStatus or its value."""
    return ", ".join(f"{str(getattr(k, 'value', k)).removeprefix('fallback_')} {n}" for k, n in counts.items())


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3g}"
