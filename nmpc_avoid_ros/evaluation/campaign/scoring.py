"""Scoring of campaign runs: one closed loop -> its record (summary.py: a family's records -> its summary).

Definitions (per scenario; y is the output, K the last sample; y* and y~ from reachability.py):

* at rest: the state moved less than REST_TOLERANCE (inf-norm) over the last REST_WINDOW samples.
* converged: |y - y*| < SETTLING_TOLERANCE (0.05) from some sample on, to the end (settled at y*).
* near: |y_K - y*| < NEAR_TOLERANCE (0.1) (the target itself if reachable, else y*);
  near_admissible: |y_K - y~| < NEAR_TOLERANCE.
* stop short (paper Remark 1): at rest but not converged; the distance is |y_K - y*|. Cause
  'obstacle_covers_target' if it stopped at y~ != y* (the avoidance cost moves the equilibrium);
  otherwise it stopped short of y~ too, 'no_passage' when the regions leave no admissible way from
  where it stopped to y~ (the family's passage test), else 'local_minimum'. van der Pol's passage is a
  trajectory of the model itself, clear (reachability.trajectory_passage), through an open corridor of free
  x2 in every x1 slice (`corridor_to_admissible`, reachability.vdp_passage, which alone was the test before
  2026-12-05); the planar families' a connected free path of the plane.
* penetration, clearance: core/loop/metrics.py (keep-in expressions and regions in force per sample).
* solver failure: a sample whose solver status is not Solve_Succeeded/Solved_To_Acceptable_Level
  (budget cuts with a feasible iterate count here, as 'truncated'); fallback: a sample that applied
  the controller's fallback. Recursive feasibility: among samples k >= 1 whose predecessor's solve
  was usable (ok/truncated), the share whose own solve was usable.
* certificate (core/loop/certificate.py, docs/certificate.md): checked samples and violations of the
  value-function decrease, also among the nominal samples (the measured state within
  NOMINAL_MISMATCH of the previous plan's x(1)), and the largest such model mismatch.

Extending: a new per-run measure is one more entry in the dict of the RECORD_SECTIONS function it
belongs to (or one more function in RECORD_SECTIONS), plus a line in summary.DEFINITIONS; a
measure derived from stored raw measures belongs in `classify` (so rebuilt summaries use the
current definition); summary keys live in summary.py. Time-measured fields are listed in
TIMED_FIELDS (see running.comparable). Where the sample's clock cut no start (`starts_cut_by_time` 0) they are
the only ones that differ between two runs of the same scenario; where it did, the outcome itself may differ
with the machine's load (campaign bicycle-0011: converged at max_solve_time 0.15 s, 4.2 short at 0.1 s).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...bag.distance import nearest_region_distance
from ...core.config.settings import ControllerSettings
from ...core.errors import NmpcError
from ...core.loop.closed_loop import ClosedLoopRun, run_closed_loop
from ...core.loop.intersample import POINTS_PER_SAMPLE, dense_run
from ...core.loop.metrics import (
    SETTLING_TOLERANCE,
    keep_in_values,
    outputs,
    penetration,
    region_values,
    settling_step,
    time_stats,
)
from ...core.nlp.search import SearchReport
from ...core.nlp.tracking import SOLVED
from ...core.problem.models import Model
from ...core.problem.regions import Region
from ...core.sample.controller import NmpcController
from ...core.sample.fallback import CANDIDATES as FALLBACK_CANDIDATES
from ...core.sample.feedback import ANSWERED_STATUS
from ...core.sample.status import StepStatus
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
#: one character per sample in the stored trace
STATUS_CODES = {StepStatus.OK: ".", StepStatus.TRUNCATED: "t", StepStatus.UNCONVERGED: "u",
                StepStatus.FALLBACK_SHIFT: "s",
                StepStatus.FALLBACK_STEADY: "S", StepStatus.FALLBACK_SAFE: "X", StepStatus.FALLBACK_RECOVERY: "R"}
#: a fallback sample this far (region plane units: m for the robots) from every region has no obstacle near
FAR_FROM_REGIONS = 1.0
#: the fallback candidates (core/sample/fallback.py), as statuses
FALLBACK_KINDS = tuple(StepStatus(f"fallback_{kind}") for kind in FALLBACK_CANDIDATES)
#: penetration from this sample on is where the input can act (x(1) is fixed by x(0), u(0) partly)
FIRST_ACTED_SAMPLE = 2
#: record fields measured in wall time (machine- and load-dependent); ('trace', 'solve_ms') is nested
TIMED_FIELDS = ("wall_s", "solve_ms", "command_ms", ("trace", "solve_ms"), ("trace", "command_ms"),
                "starts_cut_by_time")
#: a sample is nominal for the certificate when the measured state is this close (inf-norm) to the
#: previous plan's x(1) (the Euler plant: ~1e-16; the continuous plant: up to ~1 on van der Pol)
NOMINAL_MISMATCH = 1e-6
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
    y_free_planned: np.ndarray  # y~ among the regions as planned (planning_margin): the best this controller may reach


def planned_regions(regions: list[Region], settings: ControllerSettings) -> list[Region]:
    """The regions as the controller plans around them: inflated by `planning_margin` (the same list without one)."""
    margin = settings.planning_margin
    return [r.inflated(margin) for r in regions] if margin else regions


def start_feasibility(probe: NmpcController, x0: Sequence[float], y_t: Sequence[float]) -> str:
    """Is x0 in X_N (the NLP's feasible set)? A cold solve with mu = 0 (V_a is soft, so X_N does not
    depend on mu or y_t) and a generous budget: 'feasible', 'infeasible' or 'unknown'."""
    probe.reset()
    res = probe.step(x0, y_t, ())
    if StepStatus(res.status).is_usable:
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
    y_free = tools.reach.best_admissible(y_t, y_star, regions)
    planned = planned_regions(regions, settings)
    y_free_planned = y_free if planned is regions else tools.reach.best_admissible(y_t, y_star, planned)
    scored = Scored(spec, family, settings, model, run, outputs(model, run.x, run.u), y_t, y_star, y_free, regions,
                    tools.probe, y_free_planned)
    record: dict[str, Any] = {"id": spec["id"], "family": spec["family"], "index": spec["index"],
                              "spec": {k: spec[k] for k in ("x0", "target", "ellipses", "steps", "plant")}}
    for section in RECORD_SECTIONS:
        record.update(section(scored))
    record["wall_s"] = time.perf_counter() - start
    return classify(record)


def output_distance(model: Model, y: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """|y_k - reference| for outputs y [K, p], angle outputs the short way round (a pose's heading) [K]."""
    return np.linalg.norm([model.output_error(row, reference) for row in np.atleast_2d(y)], axis=1)


def outcome_section(s: Scored) -> dict[str, Any]:
    """Where the run ended relative to y_t, y* and y~, and why it stopped short."""
    run, y = s.run, s.y
    reachable = bool(np.linalg.norm(s.y_star - s.y_t) < REACHABLE_TOLERANCE)
    free_ok = bool(np.all(np.isfinite(s.y_free)))
    blocked_target = bool(not free_ok or np.linalg.norm(s.y_free - s.y_star) > REACHABLE_TOLERANCE)
    err_best = output_distance(s.model, y, s.y_star)
    err_free = output_distance(s.model, y, s.y_free) if free_ok else np.full(len(y), np.nan)
    motion = float(np.max(np.abs(run.x[-REST_WINDOW - 1:] - run.x[-1])))
    at_rest = motion < REST_TOLERANCE
    settle = settling_step(err_best, 0.0, SETTLING_TOLERANCE)
    stop_short = bool(at_rest and settle is None)
    cause, passage, corridor = None, None, None
    planned_ok = bool(np.all(np.isfinite(s.y_free_planned)))
    err_planned = float(output_distance(s.model, y[-1:], s.y_free_planned)[0]) if planned_ok else math.nan
    if stop_short:
        if blocked_target and bool(err_free[-1] < SETTLING_TOLERANCE):
            cause = "obstacle_covers_target"
        elif err_planned < SETTLING_TOLERANCE:
            # at the best admissible point among the regions as planned: their margins hold it off y~ (by 0.052-0.068
            # in five live van der Pol scenes of 500 at a slanted ellipse's edge, counted as local minima before)
            cause = "at_margin"
        else:
            # judged with the regions as the controller plans around them (region_margin and the body's radius;
            # the keep-in with keep_in_margin): a way open only without the margins is no way for this controller
            planned = planned_regions(s.regions, s.settings)
            if s.family.corridor is not None:
                corridor = bool(free_ok and s.family.corridor(run.x[-1], y[-1], s.y_free, planned, s.settings))
            passage = bool(free_ok and corridor is not False
                           and s.family.passage(run.x[-1], y[-1], s.y_free, planned, s.settings))
            cause = "local_minimum" if passage else "no_passage"
    return {
        "n_ellipses": len(s.spec["ellipses"]), "stopped_early": run.stopped,
        "reachable": reachable, "y_star": _vec(s.y_star), "y_admissible": _vec(s.y_free),
        "y_admissible_planned": _vec(s.y_free_planned), "error_to_admissible_planned": err_planned,
        "target_covered": blocked_target,
        "final_state": _vec(run.x[-1]), "final_y": _vec(y[-1]),
        "error_to_target": float(output_distance(s.model, y[-1:], s.y_t)[0]),
        "error_to_best": float(err_best[-1]), "error_to_admissible": float(err_free[-1]),
        "final_motion": motion, "at_rest": bool(at_rest),
        "settling_step": settle,
        "stop_short": stop_short, "stop_short_distance": float(err_best[-1]) if stop_short else None,
        "stop_short_beyond_admissible": float(err_free[-1]) if stop_short else None, "stop_short_cause": cause,
        "passage_to_admissible": passage, "corridor_to_admissible": corridor,
        "final_avoidance_cost": float(run.costs[-1, 1]), "final_offset_cost": float(run.costs[-1, 0]),
    }


def avoidance_section(s: Scored) -> dict[str, Any]:
    """Penetration of the keep-in set and of the regions, clearance (core/loop/metrics.py)."""
    return penetration(s.settings, s.model, s.run.x, s.run.u, s.run.regions, s.y)


def solver_section(s: Scored) -> dict[str, Any]:
    """Solver statuses, fallbacks, feasibility of the start, recursive feasibility, solve times."""
    run = s.run
    K = len(run.u)
    usable = [StepStatus(st).is_usable for st in run.status]
    pairs = sum(usable[k - 1] for k in range(1, K))
    kept = sum(usable[k - 1] and usable[k] for k in range(1, K))
    fallbacks = {kind: run.status.count(kind) for kind in FALLBACK_KINDS}
    fallback_samples = [k for k, st in enumerate(run.status) if StepStatus(st).is_fallback]
    nearest = nearest_region_distance(s.settings.plane, s.settings.output_plane, run.x[fallback_samples],
                                      s.y[fallback_samples], [run.regions[min(k, len(run.regions) - 1)]
                                                              for k in fallback_samples] if run.regions else [])
    return {
        "samples": K, "ok": run.status.count(StepStatus.OK), "truncated": run.status.count(StepStatus.TRUNCATED),
        "unconverged": run.status.count(StepStatus.UNCONVERGED),
        # a sample its prepared plan answered ran no solver (its preparation did, and converged): not a failure
        "solver_failures": int(sum(st not in SOLVED and st != ANSWERED_STATUS for st in run.solver_status)),
        "fallbacks": int(sum(fallbacks.values())), "fallback_kinds": fallbacks,
        "fallbacks_far": int(np.sum(nearest > FAR_FROM_REGIONS)),
        "initial_feasible": bool(usable[0]),
        "x0_in_feasible_set": "feasible" if usable[0] else start_feasibility(s.probe, s.spec["x0"], s.y_t),
        "rf_pairs": int(pairs), "rf_kept": int(kept),
        "non_ok_examples": [{"step": k, "status": st, "solver_status": ss}
                            for k, (st, ss) in enumerate(zip(run.status, run.solver_status))
                            if st != StepStatus.OK][:5],
        "solve_ms": time_stats(run.solve_time * 1e3),
        "command_ms": time_stats(run.command_time * 1e3),
        "budget_exhausted": int(sum(st in ("Maximum_Iterations_Exceeded", "Maximum_WallTime_Exceeded",
                                           "Maximum_CpuTime_Exceeded") for st in run.solver_status)),
    }


def passage_entries(searches: Sequence[SearchReport]) -> tuple[int, int]:
    """(entries into the passage mode, samples in it) of a run's step reports [K]. A sample is in the mode when its
    search ran the long NLP (or entered it); an entry is one after a sample that was not. A preparation enters the
    mode between the samples, and its report is not the step's: counted by `entered_passage` alone, such entries
    read 0 in the live campaign while 290 samples ran the long NLP."""
    in_mode = [r.phase == "passage" or r.entered_passage for r in searches]
    return sum(now and not before for before, now in zip([False, *in_mode], in_mode)), sum(in_mode)


def robustness_section(s: Scored) -> dict[str, Any]:
    """Penetration where the input can act and after fallbacks; local-minimum escapes.

    penetration_after_first_step: max g over x(2..K) (0 if never inside); fallback_penetration: max
    g over the `horizon` states after each fallback sample (0 without fallbacks); escapes_tried:
    samples that solved escape guesses; escapes_taken: samples whose plan came from one; passages:
    entries into the passage mode (core/sample/passage.py); passage_samples: samples spent in it;
    starts_cut_by_time: solves the sample's deadline stopped and starts its spent budget skipped (SearchReport.
    cut_by_time): where not 0, the run's outcome may depend on the machine's load.
    """
    run = s.run
    keep = keep_in_values(s.settings, s.model, run.x, run.u)
    g = region_values(s.settings, run.x, s.y, run.regions)
    passages, passage_samples = passage_entries(run.searches)
    if keep.size:
        g = np.maximum(g, keep.max(axis=1))
    after_fallback = [float(np.max(g[k + 1:k + 1 + s.settings.horizon]))
                      for k, st in enumerate(run.status) if StepStatus(st).is_fallback]
    # the same from the continuous motion under each held command (core/loop/intersample.py)
    dense, held, dense_regions = dense_run(s.settings, s.model, run.x, run.u, run.regions)
    dense_g = region_values(s.settings, dense, outputs(s.model, dense, held), dense_regions)
    if keep.size:
        dense_g = np.maximum(dense_g, keep_in_values(s.settings, s.model, dense, held).max(axis=1))
    return {
        "penetration_after_first_step": max(0.0, float(np.max(g[FIRST_ACTED_SAMPLE:], initial=-math.inf))),
        "penetration_after_first_step_between": max(0.0, float(np.max(dense_g[FIRST_ACTED_SAMPLE * POINTS_PER_SAMPLE:],
                                                                      initial=-math.inf))),
        "fallback_penetration": max([0.0, *after_fallback]),
        # the first sample's least-violating input still predicts a violation: a region cannot be
        # avoided from x0 although x0 is in X_N (whose constraints are the hard ones alone)
        "unavoidable_at_start": bool(run.predicted_violations and run.predicted_violations[0] > 1e-3),
        "escapes_tried": sum(r.guesses_tried for r in run.searches),
        "escapes_taken": sum(r.guess_taken for r in run.searches),
        "passages": passages,
        "passage_samples": passage_samples,
        "starts_cut_by_time": sum(r.cut_by_time for r in run.searches),
    }


def certificate_section(s: Scored) -> dict[str, Any]:
    """The stability certificate (core/loop/certificate.py): samples checked and violated, overall and among
    the nominal ones (the measured state within NOMINAL_MISMATCH of the previous plan's x(1)), and the
    largest model mismatch."""
    checked = [c for c in s.run.certificate if c["checked"]]
    nominal = [c for c in checked if c["model_mismatch"] is not None and c["model_mismatch"] <= NOMINAL_MISMATCH]
    mismatch = [c["model_mismatch"] for c in s.run.certificate if c["model_mismatch"] is not None]
    return {"certificate_checked": len(checked), "certificate_violations": sum(c["violated"] for c in checked),
            "certificate_checked_nominal": len(nominal),
            "certificate_violations_nominal": sum(c["violated"] for c in nominal),
            "model_mismatch_max": max(mismatch, default=None)}


def trace_section(s: Scored) -> dict[str, Any]:
    """The trajectory kept for the figures (states to 6 digits, solve times, one status code per sample)."""
    return {"trace": {"x": [_vec(r, 6) for r in s.run.x], "solve_ms": _vec(s.run.solve_time * 1e3, 3),
                      "command_ms": _vec(s.run.command_time * 1e3, 3),
                      "status": "".join(STATUS_CODES[StepStatus(st)] for st in s.run.status)}}


#: the parts of a record, in order; each maps a scored run to some of its fields
RECORD_SECTIONS: tuple[Callable[[Scored], dict[str, Any]], ...] = (
    outcome_section, avoidance_section, solver_section, robustness_section, certificate_section, trace_section)


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
