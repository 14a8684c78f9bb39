"""Local-minimum escape: more initial guesses than the shifted plan when the loop stalls.

The artificial steady output y_a moves continuously from sample to sample. When a region lies
across the steady states between y_a and the target, every y_a on the way there is inside it and
costs mu F(x_a): the shifted warm start cannot leave the local minimum in front of the region (the
campaign's 'local_minimum' stop-shorts). The escape tries initial guesses whose y_a lies beyond
each blocking stretch of the steady-state segment, reached along a straight line and along a detour
around each region in the way, on either side; the controller solves them within the sample's
budget and keeps the lowest-cost plan that satisfies the hard constraints.

When (see `EscapeGuesses.should_try`): the steady-state segment from y_a to the target is blocked
by an active region AND y_a has stalled (moved less than `STALL_TOLERANCE` in the last sample).
Without a blocking region (the paper's loops: the keep-in |x1 x2| <= 2 never covers a steady
state, where x2 = 0) nothing is tried, except for a car-like model (`EscapeGuesses.manoeuvres`: a planar
model with a heading among its outputs and `rest` rows, which cannot move sideways): with y_a stalled
more than PARK_OFFSET short of the target, it tries manoeuvres (`manoeuvre_guesses`): a sideways or
heading offset is removed only by backing up and coming in again, which no small change of its plan finds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..config.settings import ControllerSettings
from ..nlp.tracking import Buffered, NlpBase
from ..problem.models import Model
from ..problem.regions import Region
from .rollout import Rollout
from .warm_start import straight_line

#: points on the steady-state segment from y_a to the target where blocking is checked
SEGMENT_POINTS = 96
#: the segment searched runs from y_a this many times as far as the target
SEGMENT_REACH = 2.0
#: y_a has stalled when it moved less than this (output units, inf-norm) in the last sample
STALL_TOLERANCE = 1e-3
#: a detour passes this far outside a region's bounding circle, relative to its radius
DETOUR_MARGIN = 0.25
#: a steady state this far outside lambda Z still counts as in it (a solved y_a on the box's edge
#: is feasible to the solver's tolerance, not exactly)
BOX_TOLERANCE = 1e-6
#: a car-like model whose stalled y_a is farther than this from the target (output units, angles the short
#: way round) tries the manoeuvre guesses (the campaign counts a run within 0.05 as converged; its runs that
#: came in straight parked 0.005-0.03 from their goals)
PARK_OFFSET = 0.03
#: the manoeuvre guesses pass through the target's pose moved this far (m) behind and ahead along its heading
MANOEUVRE_REACH = (0.3, 0.6)
#: the label prefix of the manoeuvre guesses
MANOEUVRE = "manoeuvre_"
#: rings of outputs searched round a covered target for its nearest admissible output, and the directions on each
#: ring of a planar output (one output: both ways)
NEAREST_RINGS, NEAREST_DIRECTIONS = 48, 32


def _segment(y_from: np.ndarray, y_to: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """SEGMENT_POINTS outputs from y_from towards y_to, `reach` times as far: (t [K], Y [p, K])."""
    t = np.linspace(0.0, reach, SEGMENT_POINTS)
    return t, y_from[:, None] + (y_to - y_from)[:, None] * t[None, :]


@dataclass
class Guess:
    """One initial guess: y_a [p], x(1..N) [N, n], u(0..N-1) [N, m], and how it was made."""

    label: str
    y_a: np.ndarray
    states: np.ndarray
    inputs: np.ndarray


def bounding_circle(region: Region) -> tuple[np.ndarray, float] | None:
    """Centre [2] and radius of a circle around the region in its plane (None for unknown kinds)."""
    if hasattr(region, "semi_axes"):
        return np.asarray(region.center, float), float(max(region.semi_axes))
    if hasattr(region, "vertices"):
        pts = np.asarray(region.vertices, float)
        centre = pts.mean(axis=0)
        return centre, float(np.max(np.linalg.norm(pts - centre, axis=1)))
    return None


class EscapeGuesses:
    """Builds the escape guesses of one NLP (needs the model's closed-form steady state)."""

    def __init__(self, nlp: NlpBase, model: Model, settings: ControllerSettings) -> None:
        self.model, self.settings = model, settings
        self.horizon = nlp.layout.horizon
        self.available = model.steady_state is not None
        planar = model.planar
        #: a car-like model (a heading output, `rest` rows: it cannot move sideways, Assumption 5 fails at rest)
        self.manoeuvres = bool(self.available and model.angle_outputs and model.rest is not None and
                               planar is not None and planar.yaw is not None)
        #: a car-like model's cold guess, its own model driven towards the goal (core/sample/rollout.py)
        self._rollout = Rollout(model, settings, self.horizon) if self.manoeuvres and planar.from_command is not None \
            else None
        if not self.available:
            return
        lam = settings.steady_state_scale
        self._lo = lam * np.array([*settings.state_min, *settings.input_min], float)
        self._hi = lam * np.array([*settings.state_max, *settings.input_max], float)
        y = ca.SX.sym("y", model.p)
        par = ca.SX.sym("p", nlp.region_depth.size1_in(2))
        x_s, u_s = (ca.vertcat(v) for v in model.steady_state(y))
        # a steady state is where the plan ends (x(N) = x_a): moving obstacles as at t_N
        point = ca.Function("steady_point", [y, par], [x_s, u_s, nlp.region_depth(x_s, u_s, par,
                                                                                  self.horizon * settings.sample_time)])
        Y = ca.SX.sym("Y", model.p, SEGMENT_POINTS)
        outs = point.map(SEGMENT_POINTS)(Y, ca.repmat(par, 1, SEGMENT_POINTS))
        self._segment = Buffered(ca.Function("steady_segment", [Y, par], list(outs)))
        xs, us = ca.SX.sym("x", model.n), ca.SX.sym("u", model.m)
        self._output = Buffered(ca.Function("output", [xs, us], [model.output(xs, us)]))
        self._steady = Buffered(ca.Function("steady", [y], [x_s, u_s]))

    def should_try(self, y_a: np.ndarray, y_a_before: np.ndarray | None, y_t: np.ndarray, par: np.ndarray) -> bool:
        """Stalled (y_a moved < STALL_TOLERANCE since the last sample) with a region across the way, or for a
        car-like model parked short of the target (`parked_short`)."""
        if not self.available or y_a_before is None:
            return False
        if np.max(np.abs(y_a - y_a_before)) >= STALL_TOLERANCE:
            return False
        aim = self.aim(y_t)
        return bool(self.beyond_blocks(y_a, aim, par)) or self.parked_short(y_a, aim)

    def parked_short(self, y_a: np.ndarray, aim: np.ndarray) -> bool:
        """A car-like model (`manoeuvres`) whose y_a lies more than PARK_OFFSET from `aim` (angles the short way).
        Not only once the car rests there: while it still comes in, its plan costs more than the rest, and a
        manoeuvre that reaches y_t can cost less (campaign bicycle-0023: y_a stalled 0.139 short as the car turned in,
        and a manoeuvre guess was kept; once it rested at y_a, every manoeuvre cost more than the rest, as the
        N = 20 plan counts it, and the solver came back to the rest from each guess)."""
        return self.manoeuvres and float(np.linalg.norm(self.model.output_error(y_a, aim))) > PARK_OFFSET

    def aim(self, y_t: np.ndarray) -> np.ndarray:
        """The output [p] the segments run to: y_t, or for a y_t whose steady state is outside lambda Z
        the output of that steady state clipped into the box (twice, for an output that depends on
        the input). The segment to an unreachable y_t leaves lambda Z at once when y_a rests on the
        box's edge, so a region along the edge was never seen (campaign robot-0069: goal beyond
        y2 = 9.9, an ellipse across the edge, y_a stalled 7.6 m short)."""
        y = np.asarray(y_t, float).ravel()
        n = self.model.n
        for _ in range(2):
            x_s, u_s = self._steady(y)
            z = np.concatenate([np.ravel(x_s), np.ravel(u_s)])
            if self._in_box(z[:, None])[0]:
                break
            z = np.clip(z, self._lo, self._hi)
            y = np.ravel(self._output(z[:n], z[n:])[0]).copy()
        return y

    def beyond_blocks(self, y_from: np.ndarray, y_to: np.ndarray, par: np.ndarray) -> list[np.ndarray]:
        """Outputs just beyond each stretch of the segment from y_from towards y_to (SEGMENT_REACH times
        as far) whose steady state is inside a region, as long as they are admissible (steady state in
        lambda Z, outside every region): at most one beyond y_to."""
        # past y_to as well (up to twice as far from y_from): a region covering the target itself
        # leaves its best admissible point on the far side (beyond lambda Z the search stops)
        t, Y = _segment(y_from, y_to, SEGMENT_REACH)
        free, blocked = self._free(Y, par)
        in_box = free | blocked  # a blocked point's box membership does not matter below
        beyond = []
        inside_block = False
        for k in range(SEGMENT_POINTS):
            if blocked[k]:
                inside_block = True
            elif inside_block and free[k]:
                # one more point past the boundary, where the penalty's gradient is not pulling back
                j = k + 1 if k + 1 < SEGMENT_POINTS and free[k + 1] else k
                beyond.append(Y[:, j].copy())
                inside_block = False
                if t[j] >= 1.0:
                    break
            if (not in_box[k] and not blocked[k]) or (t[k] > 1.0 and not inside_block):
                break  # beyond lambda Z (outputs that are not steady states the plan may use), or past y_to
        if not beyond and blocked[int(np.argmin(np.abs(t - 1.0)))]:
            nearest = self.nearest_admissible(y_from, y_to, par)
            beyond += [] if nearest is None else [nearest]
        return beyond

    def nearest_admissible(self, y_from: np.ndarray, y_to: np.ndarray, par: np.ndarray) -> np.ndarray | None:
        """For y_to [p] covered by a region, the admissible output nearest it on rings round it (NEAREST_RINGS out to
        y_from's distance, NEAREST_DIRECTIONS each; one or two outputs), if it is nearer than y_from by more than two
        rings; else None. Where the far side along the segment lies outside lambda Z (a target beyond the box's
        edge) or the region's boundary has several rests, y_a stalled short of it with no stretch to pass (campaign
        robot-0112: y_a 0.99 from its target's clipped aim on the ellipse's rim, 0.36 on the box's edge)."""
        p, reach = len(y_to), float(np.linalg.norm(y_from - y_to))
        if p > 2 or reach == 0.0:
            return None
        angles = np.linspace(0.0, 2 * np.pi, NEAREST_DIRECTIONS, endpoint=False)
        directions = np.array([[-1.0, 1.0]]) if p == 1 else np.vstack([np.cos(angles), np.sin(angles)])
        step = reach / NEAREST_RINGS
        rings = np.concatenate([y_to[:, None] + k * step * directions for k in range(1, NEAREST_RINGS - 1)], axis=1)
        for start in range(0, rings.shape[1], SEGMENT_POINTS):  # in the segment function's batches, nearest first
            Y = rings[:, start:start + SEGMENT_POINTS]
            batch = np.pad(Y, ((0, 0), (0, SEGMENT_POINTS - Y.shape[1])), mode="edge")
            free = self._free(batch, par)[0][:Y.shape[1]]
            if free.any():
                return Y[:, int(np.argmax(free))].copy()
        return None

    def before_block(self, y_from: np.ndarray, y_to: np.ndarray, par: np.ndarray) -> np.ndarray | None:
        """The last admissible output on the segment from y_from to y_to before its first blocked
        stretch (one segment point short of it), or None when the way is clear or y_from itself is blocked."""
        Y = _segment(y_from, y_to, 1.0)[1]
        free, blocked = self._free(Y, par)
        if not blocked.any() or not free[0]:
            return None
        first = int(np.argmax(blocked))
        k = first - 2 if first >= 2 and free[first - 2] else first - 1
        return Y[:, k].copy() if k >= 0 and free[k] else None

    def crosses_block(self, y_from: np.ndarray, y_to: np.ndarray, par: np.ndarray) -> bool:
        """Whether a steady state on the segment from y_from to y_to is inside a region (y_to lies
        beyond a blocked stretch, seen from y_from)."""
        return bool(self._free(_segment(y_from, y_to, 1.0)[1], par)[1].any())

    def _free(self, Y: np.ndarray, par: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For outputs Y [p, SEGMENT_POINTS]: (steady state in lambda Z and outside every region, inside a region)."""
        x_s, u_s, depth = self._segment(Y.T.ravel(), par)
        z = np.vstack([x_s.reshape(SEGMENT_POINTS, -1).T, u_s.reshape(SEGMENT_POINTS, -1).T])
        in_box = self._in_box(z)
        depth = depth.reshape(SEGMENT_POINTS, -1)
        blocked = np.any(depth > 0, axis=1) if depth.size else np.zeros(SEGMENT_POINTS, bool)
        return in_box & ~blocked, blocked

    def _in_box(self, z: np.ndarray) -> np.ndarray:
        """For steady states z [n + m, K] (x_s over u_s): in lambda Z, to BOX_TOLERANCE [K]."""
        return np.all((z >= self._lo[:, None] - BOX_TOLERANCE) & (z <= self._hi[:, None] + BOX_TOLERANCE), axis=0)

    def penetration_guesses(self, x: np.ndarray, y_a: np.ndarray, y_t: np.ndarray, par: np.ndarray,
                            regions: Sequence[Region]) -> list[Guess]:
        """Guesses for a solved plan that predicts penetration (a local optimum of the penalty, e.g. x_a at
        the centre of an ellipse, where the region function's gradient vanishes, or a squeeze between
        two regions): y_a just in front of the first region on the way from the plant's output to the
        target; the plan's y_a reached around each region in the way, on either side; then the
        guesses beyond the blocking stretches (`guesses`)."""
        if not self.available:
            return []
        out = []
        y_now = self._output(x, np.zeros(self.model.m))[0].copy()
        y_before = self.before_block(y_now, self.aim(y_t), par)
        if y_before is not None:
            x_new, u_new = (v.copy() for v in self._steady(y_before))
            out.append(Guess("before_block", y_before, self._path(x, [], x_new), np.tile(u_new, (self.horizon, 1))))
        x_a, u_a = (v.copy() for v in self._steady(y_a))
        for j, region in enumerate(regions):
            for side, waypoint in zip(("left", "right"), self._detours(x, x_a, y_now, y_a, region)):
                out.append(Guess(f"around_{side}_of_region{j}", y_a.copy(), self._path(x, [waypoint], x_a),
                                 np.tile(u_a, (self.horizon, 1))))
        return out + self.guesses(x, y_a, y_t, par, regions)

    def cold_guesses(self, x: np.ndarray, y_t: np.ndarray) -> list[Guess]:
        """Guesses for a start without a plan, in the order they are tried (NmpcController._regular_starts): a plan
        that comes to rest at the plant's own output (aimed into lambda Z), then the straight line to
        y_t's steady state (clipped into the bounds). A car-like model tries first its own model driven towards the
        goal (core/sample/rollout.py: 15 FATROP iterations on the bench's first sample, against the resting plan's 116).

        Why this order (FATROP on the campaign's starts, 60 van der Pol + 30 robot): the resting plan
        converged in every start, 0.8 / 4.4 ms median, at most 4.7 / 22.5 ms; the straight line
        through the regions took 1.8 / 6.1 ms median but up to 9.5 / 62 ms and failed 2 robot starts.
        The resting plan's local optimum was worse than the IPOPT reference's in 8 + 2 starts, yet the
        closed loops were as good (campaign settling mean 21.28 / 48.70 samples against the
        reference's 21.19 / 49.27; both guesses every time: 20.94 / 48.59 at 3x the start's time).
        """
        y_rest = self.aim(self._output(x, np.zeros(self.model.m))[0].copy())
        x_r, u_r = (v.copy() for v in self._steady(y_rest))
        # the straight line is the regular start's own guess (core/sample/warm_start.py)
        y_a, states, inputs = straight_line(x, y_t, self.horizon, self.settings, self.model)
        guesses = [Guess("rest", y_rest, self._path(x, [], x_r), np.tile(u_r, (self.horizon, 1))),
                   Guess("straight", y_a, states, inputs)]
        if self._rollout is not None:  # a car-like model: first its own model driven towards the goal
            planar = self.model.planar
            goal = self._steady(self.aim(y_t))[0][[planar.x, planar.y]]
            states, inputs = self._rollout(x, goal)
            guesses.insert(0, Guess("rollout", self.aim(self._output(states[-1], inputs[-1])[0].copy()), states,
                                    inputs))
        return guesses

    def guesses(self, x: np.ndarray, y_a: np.ndarray, y_t: np.ndarray, par: np.ndarray,
                regions: Sequence[Region], beyond: list[np.ndarray] | None = None) -> list[Guess]:
        """Candidate guesses: y_a beyond each blocking stretch, straight and around each region on either side;
        with no blocking stretch, a car-like model parked short of the target: the manoeuvres to it. `beyond`: what
        `beyond_blocks` gave for y_a towards y_t's aim, if the caller has it (else computed here)."""
        out = []
        aim = self.aim(y_t)
        beyond = self.beyond_blocks(y_a, aim, par) if beyond is None else beyond
        if not beyond and self.parked_short(y_a, aim):
            return self.manoeuvre_guesses(x, aim)
        for i, y_new in enumerate(beyond):
            x_new, u_new = (v.copy() for v in self._steady(y_new))
            out.append(self._escape_guess(f"beyond{i}", x, [], x_new, y_new, u_new))
            for j, region in enumerate(regions):
                for side, waypoint in zip(("left", "right"), self._detours(x, x_new, y_a, y_new, region)):
                    out.append(self._escape_guess(f"beyond{i}_{side}_of_region{j}", x, [waypoint], x_new, y_new, u_new))
        return out

    def _escape_guess(self, label: str, x: np.ndarray, waypoints: list[np.ndarray], x_new: np.ndarray,
                      y_new: np.ndarray, u_new: np.ndarray) -> Guess:
        """y_a at y_new, the states along x -> waypoints -> x_new: the polyline, or for a car-like model its own model
        driven through the waypoints towards x_new (core/sample/rollout.py; FATROP took 160-480 ms from the polyline
        with steering-rate limits, beyond a sample's budget)."""
        if self._rollout is None:
            return Guess(label, y_new, self._path(x, waypoints, x_new), np.tile(u_new, (self.horizon, 1)))
        planar = self.model.planar
        plane = [planar.x, planar.y]
        states, inputs = self._rollout(x, x_new[plane], [w[plane] for w in waypoints])
        return Guess(label, y_new, states, inputs)

    def manoeuvre_guesses(self, x: np.ndarray, y_goal: np.ndarray) -> list[Guess]:
        """A car-like model's ways to the steady state of y_goal [p] from beside it: through the goal pose moved
        back (reversing past it, then coming in forwards) or ahead (overshooting, then backing in) by each of
        MANOEUVRE_REACH, y_a at y_goal. The states run along the polyline, not along the dynamics: the solver
        finds the steering (measured on campaign scene bicycle-0034, resting 0.057 m beside its goal, with y_a held
        at the goal by kappa 1e4: each converged to a back-and-forth manoeuvre ending there, 25-40 FATROP
        iterations; with the config's kappa 100 each came back to the rest, which costs less there)."""
        planar = self.model.planar
        x_g, u_g = (v.copy() for v in self._steady(y_goal))
        heading = np.array([np.cos(x_g[planar.yaw]), np.sin(x_g[planar.yaw])])
        out = []
        for reach in MANOEUVRE_REACH:
            for side, sign in (("behind", -1.0), ("ahead", 1.0)):
                via = x_g.copy()
                via[[planar.x, planar.y]] += sign * reach * heading
                via = np.clip(via, self.settings.state_min, self.settings.state_max)
                out.append(Guess(f"{MANOEUVRE}{side}_{reach:g}", y_goal.copy(), self._path(x, [via], x_g),
                                 np.tile(u_g, (self.horizon, 1))))
        return out

    def _detours(self, x: np.ndarray, x_new: np.ndarray, y_a: np.ndarray, y_new: np.ndarray,
                 region: Region) -> list[np.ndarray]:
        """Two waypoint states beside the region (either side of the way), or none if it is not in the way."""
        circle = bounding_circle(region)
        if circle is None:
            return []
        centre, radius = circle
        if region.frame == "state":
            plane = list(self.settings.plane)
            start, end = x[plane], x_new[plane]
        else:
            plane = list(self.settings.output_plane)
            u_now = np.zeros(self.model.m)
            start, end = self._output(x, u_now)[0][plane].copy(), y_new[plane] if y_new.size > max(plane) else None
            if end is None:
                return []
        direction = end - start
        length = float(np.linalg.norm(direction))
        if length < 1e-9:
            return []
        direction /= length
        # in the way: the segment passes within the bounding circle
        along = float(np.clip(np.dot(centre - start, direction), 0.0, length))
        if np.linalg.norm(start + along * direction - centre) > radius:
            return []
        normal = np.array([-direction[1], direction[0]])
        waypoints = []
        for sign in (1.0, -1.0):
            point = centre + sign * (1 + DETOUR_MARGIN) * radius * normal
            middle = 0.5 * (x + x_new)
            if region.frame == "state":
                middle[plane] = point
            else:
                y_mid = 0.5 * (y_a + y_new)
                y_mid[plane] = point
                middle = self._steady(y_mid)[0].copy()
            waypoints.append(np.clip(middle, self.settings.state_min, self.settings.state_max))
        return waypoints

    def _path(self, x: np.ndarray, waypoints: list[np.ndarray], x_end: np.ndarray) -> np.ndarray:
        """x(1..N) [N, n] along the polyline x -> waypoints -> x_end, evenly by arc length."""
        nodes = np.vstack([x, *waypoints, x_end])
        lengths = np.linalg.norm(np.diff(nodes, axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(lengths)])
        if arc[-1] < 1e-12:
            return np.tile(x_end, (self.horizon, 1))
        s = np.linspace(0.0, arc[-1], self.horizon + 1)[1:]
        states = np.column_stack([np.interp(s, arc, nodes[:, i]) for i in range(nodes.shape[1])])
        states[-1] = x_end  # x(N) = x_a exactly
        return states
