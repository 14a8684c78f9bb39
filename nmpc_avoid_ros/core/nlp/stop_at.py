"""An IPOPT iteration callback that ends a solve once a deadline has passed (the sample's one deadline).

IPOPT's own `max_wall_time` counts from the start of its call; a solve started late in a sample must end
by the sample's end instead: the recovery solve (core/sample/fallback.py) and the target projection
(core/nlp/projection.py) stop at `end` (time.perf_counter s) plus at most one iteration.
"""

from __future__ import annotations

import math
import time

import casadi as ca


class StopAt(ca.Callback):
    """IPOPT's iteration callback that ends the solve (User_Requested_Stop) once time.perf_counter() passes
    `end` (set it before each call; inf: never). n_x, n_g, n_p: the NLP's sizes. `name`: the Function's."""

    def __init__(self, n_x: int, n_g: int, n_p: int, name: str = "stop_at") -> None:
        ca.Callback.__init__(self)
        self._sizes = {"x": n_x, "f": 1, "g": n_g, "lam_x": n_x, "lam_g": n_g, "lam_p": n_p}
        self.end = math.inf
        self.construct(name, {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "stop"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(self._sizes[ca.nlpsol_out(i)], 1)

    def eval(self, arg: list) -> list:  # CasADi Callback's method name (no Python eval anywhere)
        return [1 if time.perf_counter() >= self.end else 0]
