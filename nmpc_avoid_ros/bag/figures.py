"""The paper's figures from plain arrays: phase portrait (Fig. 1) and time series (Fig. 2).

Inputs are `Trace`s (one per run), so the same code draws offline runs and runs read from bags.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: figures are files, never windows
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Ellipse as EllipsePatch  # noqa: E402
from matplotlib.patches import Polygon as PolygonPatch  # noqa: E402

from ..core.config.settings import ControllerSettings  # noqa: E402
from ..core.problem.models import Model  # noqa: E402
from ..core.problem.regions import Ellipse, Polygon, Region  # noqa: E402

COLORS = ("black", "tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")


@dataclass
class Trace:
    """One run: times t [K+1] s, states x [K+1, n], inputs u [K, m], artificial outputs y_a [K, p].

    regions: static regions; snapshots: (t s, state [n], moving regions at t) to draw the moving
    obstacles where they were at a few sample times, beside the state at that time; targets [K, p]:
    the target in force at each sample (nan where none), drawn as a step where each held.
    """

    label: str
    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    y_a: np.ndarray | None = None
    regions: Sequence[Region] = field(default_factory=tuple)
    snapshots: Sequence[tuple[float, np.ndarray, Sequence[Region]]] = field(default_factory=tuple)
    targets: np.ndarray | None = None


def output_rows(model: Model) -> list[int | None]:
    """For each output of the model, the state it equals (y_j = x_i: the target is drawn on x_i's row), else None."""
    rng = np.random.default_rng(0)
    xs, us = rng.normal(size=(2, model.n)), rng.normal(size=(2, model.m))
    ys = [np.asarray(model.output(x, u), float).ravel() for x, u in zip(xs, us)]
    rows: list[int | None] = []
    for j in range(model.p):
        rows.append(next((i for i in range(model.n) if all(y[j] == x[i] for x, y in zip(xs, ys))), None))
    return rows


def draw_targets(axes: Sequence[plt.Axes], t: np.ndarray, targets: np.ndarray, rows: Sequence[int | None],
                 label: str | None) -> None:
    """Each target component as a dotted step on its state's row, only where it held (nan: nothing drawn);
    the last one held to t[-1]."""
    targets = np.atleast_2d(np.asarray(targets, float))
    times = np.append(t[:len(targets)], t[-1]) if len(t) > len(targets) else t[:len(targets)]
    values = np.vstack([targets, targets[-1:]])[:len(times)]
    for j, row in enumerate(rows):
        if row is not None and row < len(axes) and j < values.shape[1]:
            axes[row].step(times, values[:, j], where="post", color="gray", ls=":", lw=1.2,
                           label=label if j == 0 else None)


def shade_product_region(ax: plt.Axes, bound: float, xlim: tuple[float, float], ylim: tuple[float, float]) -> None:
    """Shade |x1 x2| > bound in light red (the paper's non-feasible region)."""
    x1 = np.linspace(*xlim, 600)
    x2 = np.linspace(*ylim, 400)
    X1, X2 = np.meshgrid(x1, x2)
    ax.contourf(X1, X2, (np.abs(X1 * X2) > bound).astype(float), levels=[0.5, 1.5], colors=["#f4b6b6"], alpha=0.7)
    ax.plot([], [], color="#f4b6b6", linewidth=8, label=f"avoided |x1 x2| > {bound:g}")


def draw_region(ax: plt.Axes, region: Region, plane: tuple[int, int] = (0, 1), alpha: float = 0.35,
                edge: str | None = None) -> None:
    """Draw an ellipse or polygon region of the (plane[0], plane[1]) coordinates (`edge`: outline colour)."""
    style = {"facecolor": "tab:red", "alpha": alpha, "edgecolor": edge or "none", "lw": 1.2 if edge else 0}
    if isinstance(region, Ellipse):
        ax.add_patch(EllipsePatch(region.center, 2 * region.semi_axes[0], 2 * region.semi_axes[1],
                                  angle=np.degrees(region.yaw), **style))
    elif isinstance(region, Polygon):
        ax.add_patch(PolygonPatch(np.asarray(region.vertices), closed=True, **style))


def draw_snapshots(ax: plt.Axes, trace: Trace, color: str) -> None:
    """Moving obstacles at a few sample times, fainter when earlier, each beside the state of that time."""
    count = len(trace.snapshots)
    for i, (t, state, regions) in enumerate(trace.snapshots):
        alpha = 0.12 + 0.3 * (i + 1) / count
        for region in regions:
            draw_region(ax, region, alpha=alpha, edge=color)
            ax.annotate(f"{t:.1f} s", region.reference_point, fontsize=6, ha="center", color="darkred")
        ax.plot(state[0], state[1], "o", ms=6, mfc="none", mec=color, mew=1.5)
        ax.annotate(f"{t:.1f} s", (state[0], state[1]), textcoords="offset points", xytext=(4, 4), fontsize=6,
                    color=color)


def covering_limits(traces: Sequence[Trace], xlim: tuple[float, float], ylim: tuple[float, float]
                    ) -> tuple[tuple[float, float], tuple[float, float]]:
    """xlim, ylim widened (by 5 % of the span beyond a trajectory's extreme) so that every finite (x1, x2)
    of the traces is inside: the run without avoidance reaches |x2| = 2.24 beyond the paper's +-2."""
    points = np.vstack([np.asarray(t.x, float)[:, :2] for t in traces]) if traces else np.empty((0, 2))
    points = points[np.all(np.isfinite(points), axis=1)]
    limits = []
    for axis, (lo, hi) in enumerate((xlim, ylim)):
        if len(points):
            pad = 0.05 * (hi - lo)
            lo, hi = min(lo, points[:, axis].min() - pad), max(hi, points[:, axis].max() + pad)
        limits.append((float(lo), float(hi)))
    return limits[0], limits[1]


def phase_portrait(traces: Sequence[Trace], path: Path, *, product_bound: float | None = 2.0,
                   target_state: Sequence[float] | None = None, xlim=(-6.0, 6.0), ylim=(-2.0, 2.0),
                   title: str = "Phase portrait", target_states: Sequence[Sequence[float]] = (),
                   axis_names: Sequence[str] = ("x1", "x2")) -> Path:
    """Fig. 1: (x1, x2) trajectories over the shaded avoided region, x0 and the target(s) marked (`target_state`,
    and each of `target_states`); the axes span xlim, ylim and every trajectory (`covering_limits`)."""
    xlim, ylim = covering_limits(traces, xlim, ylim)
    fig, ax = plt.subplots(figsize=(7.5, 4.5), dpi=130)
    if product_bound is not None:
        shade_product_region(ax, product_bound, xlim, ylim)
    for i, trace in enumerate(traces):
        for region in trace.regions:
            draw_region(ax, region)
        draw_snapshots(ax, trace, COLORS[i % len(COLORS)])
    for i, trace in enumerate(traces):
        ax.plot(trace.x[:, 0], trace.x[:, 1], "-o", ms=2.5, lw=1.6, color=COLORS[i % len(COLORS)], label=trace.label)
    if traces:
        ax.plot(*traces[0].x[0, :2], "ks", ms=8, label="initial state")
    marks = [m for m in ([target_state] if target_state is not None else []) + list(target_states)
             if len(m) >= 2 and np.all(np.isfinite(np.asarray(m[:2], float)))]
    for i, mark in enumerate(marks):
        ax.plot(mark[0], mark[1], "kx", ms=10, mew=2.5, label="target steady state" if i == 0 else None)
    ax.set_xlim(xlim)
    ax.set_ylim(ylim)
    ax.set_xlabel(axis_names[0])
    ax.set_ylabel(axis_names[1])
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def time_series(traces: Sequence[Trace], path: Path, *, state_names: Sequence[str] = ("x1", "x2"),
                input_names: Sequence[str] = ("u",), target: Sequence[float] | None = None,
                title: str = "Time series", target_rows: Sequence[int | None] = (0,)) -> Path:
    """Fig. 2: each state and input over time (inputs as steps), y_a dashed on the first state.

    u and y_a are drawn at the first len(u) times (K of them when x has K+1 rows, i.e. when the
    state after the last sample is known; K when it is not). A trace's `targets` are drawn as steps
    where each held; `target` (one y_t for the whole run) only when no trace has them. Target component
    j goes on state row target_rows[j] (`output_rows`; None: not drawn).
    """
    n_rows = len(state_names) + len(input_names)
    fig, axes = plt.subplots(n_rows, 1, figsize=(7.5, 2.0 * n_rows + 0.6), dpi=130, sharex=True)
    axes = np.atleast_1d(axes)
    for i, trace in enumerate(traces):
        color = COLORS[i % len(COLORS)]
        for row in range(len(state_names)):
            axes[row].plot(trace.t, trace.x[:, row], color=color, lw=1.6, label=trace.label)
        if trace.y_a is not None and len(trace.y_a):
            axes[0].plot(trace.t[:len(trace.y_a)], trace.y_a[:, 0], "--", color=color, lw=1.0,
                         label=f"y_a ({trace.label})")
        for col in range(len(input_names)):
            axes[len(state_names) + col].step(trace.t[:len(trace.u)], trace.u[:, col], where="post", color=color,
                                              lw=1.6, label=trace.label)
    drawn = [trace for trace in traces if trace.targets is not None and len(trace.targets)]
    for i, trace in enumerate(drawn):
        draw_targets(axes[:len(state_names)], trace.t, trace.targets, target_rows, "target" if i == 0 else None)
    if not drawn and target is not None:
        for j, row in enumerate(target_rows):
            if row is not None and j < len(target) and np.isfinite(target[j]):
                axes[row].axhline(target[j], color="gray", ls=":", lw=1.0, label="target" if j == 0 else None)
    for ax, name in zip(axes, [*state_names, *input_names]):
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="lower right")
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def value_function_plot(series: Sequence[tuple[str, np.ndarray, np.ndarray, np.ndarray]], path: Path,
                        title: str = "Value function V_N and certificate") -> Path:
    """V_N per sample (log scale) per run: (label, sample k [K], V_N [K], violated [K] bool); violations marked x."""
    fig, ax = plt.subplots(figsize=(7.5, 3.2), dpi=130)
    for i, (label, t, values, violated) in enumerate(series):
        color = COLORS[i % len(COLORS)]
        shown = np.where(values > 0, values, np.nan)  # log scale: V_N = 0 exactly at a steady state
        ax.semilogy(t, shown, "-", lw=1.4, color=color, label=f"{label} ({int(np.sum(violated))} violations)")
        if np.any(violated):
            ax.semilogy(t[violated], shown[violated], "x", ms=8, mew=2, color="tab:red")
    ax.set_xlabel("sample k")
    ax.set_ylabel("V_N")
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def target_states(model: Model, targets: Sequence[Sequence[float]]) -> list[list[float]]:
    """Where each distinct finite target y_t sits in the (x1, x2) plane: van der Pol's steady state [y_t, 0],
    else the target's first two values (the robots' position)."""
    out: list[list[float]] = []
    for target in targets:
        target = [float(v) for v in target]
        if not target or not np.all(np.isfinite(target)):
            continue
        mark = [target[0], 0.0] if model.name == "van_der_pol" else target[:2]
        if mark not in out:
            out.append(mark)
    return out


def run_figures(traces: Sequence[Trace], settings: ControllerSettings, target: Sequence[float] | None, out: Path,
                what: str) -> tuple[Path, Path]:
    """OUT/phase_portrait.png and OUT/time_series.png of runs of one configuration (the paper's
    shaded region when its keep-in |x1 x2| <= 2 is configured); `what` ends the titles. The targets
    marked and drawn are the traces' `targets` where they have them, else `target` (None or nan: none)."""
    model = settings.build_model()
    paper_region = model.name == "van_der_pol" and any("x1*x2" in k.replace(" ", "") for k in settings.keep_in)
    lo, hi = settings.state_min, settings.state_max
    held = [row for trace in traces if trace.targets is not None for row in np.atleast_2d(trace.targets)]
    marks = target_states(model, held or ([target] if target is not None else []))
    phase = phase_portrait(traces, out / "phase_portrait.png", product_bound=2.0 if paper_region else None,
                           target_states=marks, xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]),
                           title=f"Phase portrait {what}", axis_names=model.state_names[:2])
    series = time_series(traces, out / "time_series.png", state_names=model.state_names,
                         input_names=model.input_names, target=target, title=f"States, input and y_a {what}",
                         target_rows=output_rows(model))
    return phase, series
