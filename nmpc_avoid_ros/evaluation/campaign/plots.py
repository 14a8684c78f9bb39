"""Summary plots of a campaign (matplotlib, Agg): errors, penetration, solve times, examples.

Reads the per-scenario records of `campaign.jsonl` (with their traces); see evaluation/campaign/.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ...bag.figures import draw_region, plt, shade_product_region
from ...core.config.settings import ControllerSettings, load_params_file
from ...core.loop.metrics import SETTLING_TOLERANCE
from ...core.problem.regions import Region
from .scenarios import FAMILIES, spec_ellipses

FAMILY_TITLES = {f.key: f.title for f in FAMILIES}
OUTCOMES = (("converged", "tab:green"), ("stop short", "tab:orange"), ("not at rest", "tab:red"),
            ("other", "tab:gray"))


def outcome(rec: Mapping[str, Any]) -> str:
    """'converged', 'stop short', 'not at rest' or 'other' (at rest near y* but not settled for good)."""
    if rec["converged"]:
        return "converged"
    if rec["stop_short"]:
        return "stop short"
    if not rec["at_rest"]:
        return "not at rest"
    return "other"


def _families(records: Sequence[Mapping[str, Any]]) -> list[str]:
    return list(dict.fromkeys(r["family"] for r in records))


def _family_panels(records: Sequence[Mapping[str, Any]]) -> tuple[plt.Figure, list[tuple[Any, str, list]]]:
    """One panel per model family, side by side: the figure and (axes, family, its records) per panel."""
    fams = _families(records)
    fig, axes = plt.subplots(1, len(fams), figsize=(5.5 * len(fams), 3.6), dpi=110, squeeze=False)
    return fig, [(ax, fam, [r for r in records if r["family"] == fam]) for ax, fam in zip(axes[0], fams)]


def _label_panel(ax: Any, fam: str, title: str, xlabel: str, ylabel: str = "scenarios", **title_kw: Any) -> None:
    """Title "<family>: <title>", axis labels, legend and grid of one family panel."""
    ax.set_title(f"{FAMILY_TITLES.get(fam, fam)}: {title}", **title_kw)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)


def _save(fig: plt.Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def final_error_plot(records: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """Histogram of |y_K - y*| (log scale) per family, stacked by outcome."""
    fig, panels = _family_panels(records)
    for ax, fam, recs in panels:
        bins = np.linspace(-12, 2, 57)
        data, colors, labels = [], [], []
        for name, color in OUTCOMES:
            vals = [math.log10(max(r["error_to_best"], 1e-12)) for r in recs if outcome(r) == name]
            if vals:
                data.append(vals)
                colors.append(color)
                labels.append(f"{name} ({len(vals)})")
        ax.hist(data, bins=bins, stacked=True, color=colors, label=labels)
        ax.axvline(math.log10(SETTLING_TOLERANCE), color="k", ls="--", lw=1, label=f"tolerance {SETTLING_TOLERANCE:g}")
        _label_panel(ax, fam, "final distance to y*", "log10 |y_K - y*|  (y* = best reachable point)")
    return _save(fig, path)


def penetration_plot(records: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """Histogram of the max penetration per run (runs that never entered a region are counted apart)."""
    fig, panels = _family_panels(records)
    for ax, fam, recs in panels:
        bins = np.linspace(-10, 1, 45)
        for key, color, label in (("max_penetration_keep_in", "tab:purple", "keep-in (expression g)"),
                                  ("max_penetration_obstacles", "tab:red", "ellipses (1 - r^2)")):
            vals = [r[key] for r in recs]
            pos = [math.log10(v) for v in vals if v > 0]
            zero = sum(v <= 0 for v in vals)
            ax.hist(pos, bins=bins, alpha=0.6, color=color, label=f"{label}: {zero} runs never inside")
        _label_panel(ax, fam, "deepest sampled point inside a region", "log10 max penetration")
    return _save(fig, path)


def solve_time_plot(records: Sequence[Mapping[str, Any]], settings: Mapping[str, ControllerSettings],
                    path: Path) -> Path:
    """Distribution of every sample's solve time (ms, log bins), with the budget and Ts marked."""
    fig, panels = _family_panels(records)
    for ax, fam, recs in panels:
        vals = np.concatenate([r["trace"]["solve_ms"] for r in recs])
        vals = np.maximum(vals, 1e-2)
        ax.hist(vals, bins=np.logspace(math.log10(vals.min()), math.log10(max(vals.max(), 10 * vals.min())), 60),
                color="tab:blue")
        s = settings.get(fam)
        if s is not None:
            ax.axvline(s.max_solve_time * 1e3, color="tab:orange", ls="--", label=f"budget {s.max_solve_time:g} s")
            ax.axvline(s.sample_time * 1e3, color="tab:red", ls=":", label=f"Ts {s.sample_time:g} s")
        ax.set_xscale("log")
        ax.set_yscale("log")
        p50, p99 = np.percentile(vals, [50, 99])
        _label_panel(ax, fam, f"{len(vals)} solves, median {p50:.0f} ms, p99 {p99:.0f} ms, max {vals.max():.0f} ms",
                     "solve time (ms)", "samples", fontsize=9)
    return _save(fig, path)


def _regions(rec: Mapping[str, Any]) -> list[Region]:
    return spec_ellipses(rec["spec"])


EXAMPLE_PICKS: tuple[tuple[str, Callable[[Mapping[str, Any]], bool]], ...] = (
    ("converged among ellipses", lambda r: r["converged"] and r["n_ellipses"] >= 2),
    ("stop short: region covers y*", lambda r: r["stop_short_cause"] == "obstacle_covers_target"),
    ("stop short: no passage", lambda r: r["stop_short_cause"] == "no_passage"),
    ("stop short: local minimum", lambda r: r["stop_short_cause"] == "local_minimum"),
    ("unreachable target", lambda r: not r["reachable"] and r["converged"]),
    ("not at rest", lambda r: not r["at_rest"]),
    ("fallback used", lambda r: r["fallbacks"] > 0),
)


def pick_examples(records: Sequence[Mapping[str, Any]], limit: int = 4) -> list[tuple[str, Mapping[str, Any]]]:
    """Up to `limit` illustrative scenarios (first match of each kind, in id order)."""
    out = []
    for label, pred in EXAMPLE_PICKS:
        match = next((r for r in sorted(records, key=lambda r: r["id"]) if pred(r)), None)
        if match is not None and len(out) < limit:
            out.append((label, match))
    return out


def draw_moving(ax: plt.Axes, regions: Sequence[Region], x: np.ndarray, sample_time: float) -> None:
    """Moving regions: faint at the start, their centres' tracks dashed, solid at the closest approach
    to the run's positions x [K+1, 2+] (each region where it was at that sample, k Ts)."""
    times = np.arange(len(x)) * sample_time
    for region in regions:
        track = np.array([region.at(t).reference_point for t in times])
        depths = [region.at(t).depth(p[:2]) for t, p in zip(times, x)]
        closest = int(np.argmax(depths))
        draw_region(ax, region, alpha=0.15)
        ax.plot(track[:, 0], track[:, 1], "--", lw=0.8, color="tab:red")
        draw_region(ax, region.at(times[closest]), alpha=0.5, edge="darkred")
        ax.plot(*x[closest, :2], "o", ms=6, mfc="none", mec="darkred")
        ax.annotate(f"{times[closest]:.1f} s", tuple(x[closest, :2]), textcoords="offset points", xytext=(4, 4),
                    fontsize=6, color="darkred")


def examples_plot(records: Sequence[Mapping[str, Any]], fam: str, path: Path,
                  settings: ControllerSettings | None = None) -> Path | None:
    """Phase portraits (van der Pol) or paths (robot) of a few illustrative scenarios."""
    picks = pick_examples([r for r in records if r["family"] == fam])
    if not picks:
        return None
    cols = 2 if len(picks) > 1 else 1
    rows = math.ceil(len(picks) / cols)
    vdp = fam == "vdp"
    fig, axes = plt.subplots(rows, cols, figsize=(6.2 * cols, (3.6 if vdp else 5.2) * rows), dpi=100, squeeze=False)
    for ax in axes.ravel()[len(picks):]:
        ax.axis("off")
    for ax, (label, rec) in zip(axes.ravel(), picks):
        x = np.asarray(rec["trace"]["x"])
        if vdp:
            xlim, ylim = (-6.5, 6.5), (-2.2, 2.2)
            shade_product_region(ax, 2.0, xlim, ylim)
            ax.add_patch(plt.Rectangle((-6, -2), 12, 4, fill=False, ec="k", lw=0.8))
            target_pt, best_pt = (rec["spec"]["target"][0], 0), (rec["y_star"][0], 0)
            adm_pt = (rec["y_admissible"][0], 0)
        else:
            xlim = ylim = (-11.5, 11.5)
            ax.add_patch(plt.Rectangle((-10, -10), 20, 20, fill=False, ec="k", lw=0.8))
            # a pose goal (x, y, heading) is drawn at its position, the heading as an arrow below
            target_pt, best_pt, adm_pt = (tuple(np.asarray(v, float)[:2])
                                          for v in (rec["spec"]["target"], rec["y_star"], rec["y_admissible"]))
            ax.set_aspect("equal")
        regions = _regions(rec)
        for region in regions:
            if not region.moving:
                draw_region(ax, region, alpha=0.45)
        if settings is not None and any(r.moving for r in regions):
            draw_moving(ax, [r for r in regions if r.moving], x, settings.sample_time)
        ax.plot(x[:, 0], x[:, 1], "-o", ms=2, lw=1.3, color="tab:blue", label="closed loop")
        ax.plot(x[0, 0], x[0, 1], "ks", ms=6, label="start")
        ax.plot(*target_pt, "kx", ms=9, mew=2, label="target y_t")
        if not vdp and len(rec["spec"]["target"]) >= 3:
            heading = float(rec["spec"]["target"][2])
            ax.annotate("", xy=(target_pt[0] + 1.2 * math.cos(heading), target_pt[1] + 1.2 * math.sin(heading)),
                        xytext=target_pt, arrowprops={"arrowstyle": "->", "color": "k", "lw": 1.2})
        ax.plot(*best_pt, "o", mfc="none", mec="tab:green", ms=10, mew=1.5, label="best reachable y*")
        if np.all(np.isfinite(adm_pt)) and not np.allclose(adm_pt, best_pt):
            ax.plot(*adm_pt, "D", mfc="none", mec="tab:purple", ms=8, label="best admissible y~")
        ax.set_xlim(xlim)
        ax.set_ylim(ylim)
        ax.set_xlabel("x1" if vdp else "px (m)")
        ax.set_ylabel("x2" if vdp else "py (m)")
        extra = f", stopped {rec['stop_short_distance']:.2f} short" if rec["stop_short"] else ""
        ax.set_title(f"{rec['id']}: {label}{extra}", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="lower right")
    return _save(fig, path)


def write_plots(out: Path, records: Sequence[Mapping[str, Any]], configs: Mapping[str, str]) -> list[Path]:
    """All campaign plots into `out`; returns the files written."""
    settings = {fam: ControllerSettings.from_params(load_params_file(cfg).section("controller"))
                for fam, cfg in configs.items()}
    paths = [final_error_plot(records, out / "final_error.png"), penetration_plot(records, out / "penetration.png"),
             solve_time_plot(records, settings, out / "solve_time.png")]
    for fam in _families(records):
        p = examples_plot(records, fam, out / f"examples_{fam}.png", settings.get(fam))
        if p is not None:
            paths.append(p)
    return paths
