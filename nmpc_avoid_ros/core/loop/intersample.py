"""Clearance between the samples: the plant's continuous motion under each held command, checked densely.

A sampled-data loop can satisfy every constraint at the samples and still cut through a region
between them (a chord across an obstacle's edge, or a fast state stepping over a small one). The
check here integrates the continuous model from each recorded state x(k) under its command u(k)
over one sample and evaluates the regions at `per_sample` evenly spaced times (the samples
included), with moving regions where they are at each of those times.

The integration is RK4 with SUBSTEPS steps per checked point, in one CasADi map over all
samples: for the shipped models (Ts = 0.25-0.5 s, 10 points per sample) its error is far below
the 1e-3 of a clearance bound, and a 100-sample run takes milliseconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..config.settings import ControllerSettings
from ..problem.models import Model
from ..problem.regions import Region
from .metrics import penetration

#: RK4 steps per checked point
SUBSTEPS = 8
#: checked points per sample (the goal of issue 22: 10x the sample rate)
POINTS_PER_SAMPLE = 10


def dense_states(model: Model, x: np.ndarray, u: np.ndarray, sample_time: float,
                 per_sample: int = POINTS_PER_SAMPLE, delays: np.ndarray | None = None) -> np.ndarray:
    """States at t_k + j Ts / per_sample, j = 0..per_sample - 1, for every sample k < K, and x(K).

    x [K+1, n] (or [K, n]: then no final state is appended), u [K, m] -> [K per_sample (+1), n]; each
    sample starts from its recorded x(k), so a model mismatch does not accumulate across samples.
    delays [K] (s): u(k) acts that long after x(k), the previous command until then (a latency-compensated
    loop, core/sample/latency.py); None or zeros: at once.
    """
    x, u = np.atleast_2d(np.asarray(x, float)), np.atleast_2d(np.asarray(u, float))
    K = len(u)
    if delays is not None and np.any(np.asarray(delays, float)[:K] > 0):
        return _delayed_dense_states(model, x, u, sample_time, per_sample, np.asarray(delays, float))
    path = model.discrete_path(sample_time, "rk4", per_sample * SUBSTEPS).map(K)
    points = np.asarray(path(x[:K].T, u.T), float)  # [n, K * per_sample * SUBSTEPS]
    points = points.reshape(model.n, K, per_sample * SUBSTEPS)[:, :, SUBSTEPS - 1::SUBSTEPS]  # j = 1..per
    # sample k's points: x(k) then its first per_sample - 1 checked points
    within = np.concatenate([x[:K].T[:, :, None], points[:, :, :-1]], axis=2)  # [n, K, per_sample]
    dense = within.transpose(1, 2, 0).reshape(K * per_sample, model.n)
    return np.vstack([dense, x[K:K + 1]]) if len(x) > K else dense


def _delayed_dense_states(model: Model, x: np.ndarray, u: np.ndarray, sample_time: float, per_sample: int,
                          delays: np.ndarray) -> np.ndarray:
    """`dense_states` where u(k) acts delays[k] s after x(k) (u(k-1) until then; the first: at once)."""
    K = len(u)
    flow = model.flow("rk4", SUBSTEPS)
    rows = []
    for k in range(K):
        before = u[k - 1] if k else u[k]
        delay = min(max(float(delays[k]), 0.0), sample_time)
        switched = np.asarray(flow(x[k], before, delay), float).ravel()
        for j in range(per_sample):
            t = j * sample_time / per_sample
            point = flow(x[k], before, t) if t <= delay else flow(switched, u[k], t - delay)
            rows.append(np.asarray(point, float).ravel())
    dense = np.array(rows).reshape(K * per_sample, model.n)
    return np.vstack([dense, x[K:K + 1]]) if len(x) > K else dense


def dense_run(settings: ControllerSettings, model: Model, x: np.ndarray, u: np.ndarray,
              regions: Sequence[Sequence[Region]], times: Sequence[float] | None = None,
              per_sample: int = POINTS_PER_SAMPLE, delays: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, list[tuple[Region, ...]]]:
    """The dense states [K per_sample + 1, n] (`dense_states`), the command held at each [same rows, m], and
    the regions in force at each, moving ones moved to the point's time (`Region.at`).

    x [K+1, n] states the samples solved on (+ final), u [K, m] commands, regions [K] the set in force
    at each sample, times [K] the sample times (s; default k Ts), delays [K] as in `dense_states`."""
    K = len(u)
    ts = settings.sample_time
    dense = dense_states(model, x, u, ts, per_sample, delays)
    t0 = np.arange(K) * ts if times is None else np.asarray(times, float)
    u2 = np.atleast_2d(np.asarray(u, float))
    held = np.repeat(u2, per_sample, axis=0)
    if delays is not None:  # before its delay, a sample's points are under the previous command
        offsets = np.tile(np.arange(per_sample) * ts / per_sample, K)
        sample_of = np.repeat(np.arange(K), per_sample)
        early = offsets <= np.asarray(delays, float)[sample_of]
        held[early] = u2[np.maximum(sample_of[early] - 1, 0)]
    held = np.vstack([held, held[-1:]])[:len(dense)]
    dense_regions: list[tuple[Region, ...]] = []
    for k in range(len(dense)):
        sample = min(k // per_sample, K - 1)
        in_force = regions[min(sample, len(regions) - 1)] if len(regions) else ()
        t = t0[sample] + (k - sample * per_sample) * ts / per_sample
        dense_regions.append(tuple(r.at(t) if r.moving else r for r in in_force))
    return dense, held, dense_regions


def clearance_between_samples(settings: ControllerSettings, model: Model, x: np.ndarray, u: np.ndarray,
                              regions: Sequence[Sequence[Region]], times: Sequence[float] | None = None,
                              per_sample: int = POINTS_PER_SAMPLE) -> dict[str, Any]:
    """Penetration and clearance (core/loop/metrics.py `penetration`, same keys) over the dense states
    of `dense_run` (same arguments)."""
    dense, held, dense_regions = dense_run(settings, model, x, u, regions, times, per_sample)
    return penetration(settings, model, dense, held, dense_regions)
