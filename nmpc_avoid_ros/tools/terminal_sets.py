"""The terminal sets measured: the paper's run, the admissible y_a and X_N for both terminal conditions.

    python -m nmpc_avoid_ros.tools.terminal_sets [--horizons 2 3 4 5 6 7 8] [--out docs] [--grid 25 9]

For each horizon N and each `terminal` (equality, set):
* the paper's run (x0 = [-5, 0], y_t = 5, Euler plant, 50 samples) with mu = 1e8 and mu = 0: settling step
  (|x1 - 5| < 0.05 for good), max |x1 x2|, statuses;
* from x0 = [-5, 0] the range of artificial outputs y_a that P_N admits (regions off): the smallest and the
  largest y_a, each the optimum of P_N with V_o pulling y_a far out (y_t = -+100) and zero stage weights (a
  local solver: each end is an admissible y_a, the true range can only be wider);
* X_N on a grid of |x1| <= 6, |x2| <= 2 (regions off) at each horizon: the grid points from which IPOPT finds a
  feasible plan (from a resting guess: a lower estimate of X_N); the figure draws N = 5.
Writes terminal_set.json and terminal_set.png (the certified terminal sets over the state plane) to --out.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ..core.config.settings import ControllerSettings
from ..core.loop.closed_loop import max_abs_product, run_closed_loop, settling_step
from ..core.nlp.terminal import terminal_ingredients
from ..core.nlp.tracking import SOLVED, TrackingNlp
from ..core.sample.controller import NmpcController

X0 = np.array([-5.0, 0.0])
TARGET = 5.0
STEPS = 50
TERMINALS = ("equality", "set")
#: the y_a whose terminal sets the figure draws
SHOWN_Y = (-5.9, -5.0, -3.0, 0.0, 3.0, 5.0, 5.9)
#: the initial y_a of the admissible range's extra starts
RANGE_STARTS = (-5.9, -3.0, 0.0, 3.0, 5.9)


def paper_run(horizon: int, terminal: str, mu: float) -> dict:
    """Settling step, max |x1 x2| and statuses of the paper's run at this horizon."""
    controller = NmpcController(ControllerSettings(horizon=horizon, terminal=terminal, mu=mu))
    start = time.perf_counter()
    run = run_closed_loop(controller, X0, [TARGET], STEPS, "euler")
    return {"settling_step": settling_step(run.x[:, 0], TARGET, 0.05), "max_abs_x1x2": max_abs_product(run.x),
            "not_ok": sum(s != "ok" for s in run.status), "seconds": time.perf_counter() - start}


class Feasibility:
    """P_N without regions, solved with chosen parameters from a resting guess."""

    def __init__(self, horizon: int, terminal: str, base: ControllerSettings | None = None) -> None:
        base = base or ControllerSettings()
        self.nlp = TrackingNlp(base.replace(horizon=horizon, terminal=terminal, keep_in=(), max_iterations=500))
        self.n_slots = self.nlp.slot_layout.size

    def solve(self, x0: np.ndarray, y_t: float, kappa: float, weight: float, y_guess: float | None = None
              ) -> tuple[bool, np.ndarray]:
        """(solved and feasible, w) of P_N from x0 with V_o = kappa (y_a - y_t)^2 and stage weights `weight`, from
        a plan resting at x0 with y_a = y_guess (default x0's output)."""
        nlp, layout = self.nlp, self.nlp.layout
        par = nlp.parameters(x0, np.array([y_t]), np.zeros(self.n_slots), kappa=kappa, mu=0.0,
                             state_weights=np.full(layout.n, weight), input_weights=np.full(layout.m, weight),
                             keep_in_active=np.zeros(layout.n_keep_in))
        guess = nlp.fill_slacks(layout.join_w(np.zeros((layout.horizon, 1)), np.tile(x0, (layout.horizon, 1)),
                                              x0[:1] if y_guess is None else [y_guess], None), par)
        w, _, _, stats, _ = nlp.solve_here(guess, par, np.zeros(layout.n_w), np.zeros(nlp.lbg.size))
        ok = str(stats.get("return_status")) in SOLVED and nlp.violation(w, par) < 1e-6
        return ok, w

    def y_a_range(self, x0: np.ndarray) -> list[float | None]:
        """[smallest, largest] admissible y_a from x0 (None where no feasible plan was found): the extremes over
        starts with y_a at x0's output and at RANGE_STARTS (a local solver: each start may end in a local optimum)."""
        ends = []
        for y_t, pick in ((-100.0, min), (100.0, max)):
            found = []
            for y_guess in (None, *RANGE_STARTS):
                ok, w = self.solve(x0, y_t, 1e4, 1e-9, y_guess)
                if ok:
                    found.append(float(self.nlp.layout.y_a(w)[0]))
            ends.append(pick(found) if found else None)
        return ends

    def feasible_grid(self, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
        """[len(x2), len(x1)] bool: a feasible plan found from (x1, x2)."""
        return np.array([[self.solve(np.array([a, b]), a, 1.0, 1.0)[0] for a in x1] for b in x2])


def draw(ingredients, records: dict, out: Path, x1: np.ndarray, x2: np.ndarray) -> Path:
    """terminal_set.png: the certified sets {V_f <= alpha(y_a)} in the state plane with X_N at N = 5, the
    level alpha(y_a), and the admissible y_a ranges per horizon."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 11))
    ax = axes[0]
    grid = records["x_n_grid"]
    xx, yy = np.meshgrid(x1, x2)
    for terminal, marker, colour in (("equality", "s", "0.75"), ("set", ".", "tab:green")):
        feasible = np.array(grid[terminal], bool)
        ax.scatter(xx[feasible], yy[feasible], marker=marker, s=30 if marker == "s" else 12, color=colour,
                   label=f"X_5 ({terminal}): {feasible.mean():.0%} of the grid")
    angle = np.linspace(0, 2 * np.pi, 200)
    for y, colour in zip(SHOWN_Y, matplotlib.colormaps["viridis"](np.linspace(0, 0.9, len(SHOWN_Y)))):
        p, alpha = ingredients.cost_matrix(y), ingredients.alpha(y)
        w, v = np.linalg.eigh(p)
        ellipse = v @ (np.sqrt(alpha / w)[:, None] * np.vstack([np.cos(angle), np.sin(angle)]))
        ax.fill(y + ellipse[0], ellipse[1], color=colour, alpha=0.25)
        ax.plot(y + ellipse[0], ellipse[1], color=colour, lw=1.2)
        ax.plot([y], [0], "+", color=colour)
    ax.plot([], [], color="tab:blue", lw=1.2, label=f"terminal sets {{V_f <= alpha(y_a)}} around (y_a, 0), y_a = "
                                                       f"{', '.join(f'{y:g}' for y in SHOWN_Y)}")
    ax.set(xlabel="x1", ylabel="x2", xlim=(-6.3, 6.3), ylim=(-2.2, 2.2), title="van der Pol, Euler Ts = 0.5 s")
    ax.legend(loc="lower left", fontsize=7, framealpha=0.9)
    ax = axes[1]
    ys = np.linspace(ingredients.y_low, ingredients.y_high, 400)
    extents = np.array([np.sqrt(ingredients.alpha(y) * np.diag(np.linalg.inv(ingredients.cost_matrix(y))))
                        for y in ys])
    ax.semilogy(ys, extents[:, 0], label="half-width in x1")
    ax.semilogy(ys, extents[:, 1], label="half-width in x2")
    ax.semilogy(ingredients.grid_y, ingredients.grid_alpha, ".", ms=2, label="certified alpha (grid)")
    ax.semilogy(ys, [ingredients.alpha(y) for y in ys], label="alpha(y_a) used (fit below the certified)")
    ax.set(xlabel="y_a", title="terminal set size")
    ax.legend(fontsize=8)
    ax = axes[2]
    for offset, terminal in ((-0.15, "equality"), (0.15, "set")):
        for horizon, (lo, hi) in records["y_a_range"][terminal].items():
            if lo is not None and hi is not None:
                ax.plot([int(horizon) + offset] * 2, [lo, hi], lw=5, color="0.5" if terminal == "equality"
                        else "tab:green", label=terminal if horizon == next(iter(records["y_a_range"][terminal]))
                        else None)
    ax.set(xlabel="horizon N", ylabel="admissible y_a from x0 = [-5, 0]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "terminal_set.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--horizons", type=int, nargs="+", default=[2, 3, 4, 5, 6, 7, 8])
    parser.add_argument("--grid", type=int, nargs=2, default=[25, 9], metavar=("N1", "N2"))
    parser.add_argument("--out", type=Path, default=Path("docs"))
    args = parser.parse_args(argv)
    settings = ControllerSettings(terminal="set")
    start = time.perf_counter()
    ingredients = terminal_ingredients(settings, settings.build_model())
    records: dict = {"ingredients": {"seconds": ingredients.seconds, "cache": ingredients.cache,
                                     "lookup_seconds": time.perf_counter() - start, "margin": ingredients.margin,
                                     "y_range": [ingredients.y_low, ingredients.y_high],
                                     "midpoint_ratio": ingredients.midpoint_ratio, "fit_error": ingredients.fit_error},
                     "runs": [], "y_a_range": {t: {} for t in TERMINALS}, "x_n_grid": {}}
    print(f"ingredients: {records['ingredients']}")
    for horizon in args.horizons:
        for terminal in TERMINALS:
            for mu in (1e8, 0.0):
                row = {"horizon": horizon, "terminal": terminal, "mu": mu, **paper_run(horizon, terminal, mu)}
                records["runs"].append(row)
                print(row, flush=True)
            records["y_a_range"][terminal][horizon] = Feasibility(horizon, terminal).y_a_range(X0)
            print(terminal, horizon, "y_a range", records["y_a_range"][terminal][horizon], flush=True)
    x1, x2 = np.linspace(-6, 6, args.grid[0]), np.linspace(-2, 2, args.grid[1])
    records["x_n_share"] = {t: {} for t in TERMINALS}
    records["x_n_missing_with_set"] = {}
    for horizon in args.horizons:
        grids = {t: Feasibility(horizon, t).feasible_grid(x1, x2) for t in TERMINALS}
        for terminal, grid in grids.items():
            records["x_n_share"][terminal][horizon] = float(grid.mean())
            if horizon == 5:
                records["x_n_grid"][terminal] = grid.astype(int).tolist()
        # grid points the equality solved from and the set did not (a local solver's miss or a real loss)
        records["x_n_missing_with_set"][horizon] = int(np.sum(grids["equality"] & ~grids["set"]))
        print(f"N = {horizon}: X_N share", {t: records["x_n_share"][t][horizon] for t in TERMINALS},
              "equality-only points", records["x_n_missing_with_set"][horizon], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "terminal_set.json").write_text(json.dumps(records, indent=1))
    print("wrote", draw(ingredients, records, args.out, x1, x2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
