"""The timing of a real-time loop read back from its bag, and a plant that replays it.

A real-time plant node (nodes/plant.py) publishes its state every period P = 1 / `publish_rate` s
(a tick), each period lasting exactly P of simulated time. A command acts from the moment it
arrives: the period it arrives in is integrated under the command in force up to the arrival
(s seconds after the period's tick, 0 <= s <= P) and under the new one for the rest. Until the
first command the plant holds x0 (`hold_until_command`). The controller solves on its timer on
the latest state and its command arrives some time later (its solve, or `command_latency`), so a
sample does not last exactly `sample_time` and its command does not act from its start.

All of it is in the bag: the states, one per tick, are deterministic functions of the arrival
times, so `recorded_timing` recovers each command's arrival period by period from the recorded
states (scipy least squares on the one scalar s in [0, P] per arrival, started from the
command's log time), checks that the recorded commands applied that way reproduce every solved
state, and `TimedPlant` replays a loop with that timing. Bags of the earlier plant, which applied a
command to the whole period it arrived in (or to the next one when it came after the tick was
due), are the special case s = 0: a whole number of plant steps late.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..bag.analysis import RecordedRun, controller_samples
from ..bag.mcap_io import Bag
from ..core.loop.closed_loop import Plant

#: m.s.: the recorded commands applied with the recovered timing reproduce the solved states this closely
#: (measured: 2.8e-9 on a 47 s live bag of the causal plant, the commands applied open loop from its first state;
#: 1e-13 on simulated ones, test/test_recorded_timing.py; 0 on the earlier plant's)
TIMING_TOLERANCE = 1e-6
#: m.s.: a period's recorded end state fits a timing when it is reproduced this closely (the plant's own
#: integration, DOP853 at rtol 1e-10, repeated with the same steps: 0 without an arrival, <= 1e-11 with one)
FIT_TOLERANCE = 1e-8
#: the most commands fitted to arrive within one plant period (a late cover and the sample's own command)
MAX_ARRIVALS_PER_PERIOD = 3


@dataclass
class Arrival:
    """A recorded command reaching the plant `at` s after the tick of the first state a sample solved on.
    `sample`: the sample whose command it is (its replayed command is applied); None: a command the
    controller sent besides its samples' (a late cover, the deactivation), replayed as recorded."""

    at: float
    value: np.ndarray
    sample: int | None


@dataclass
class RecordedTiming:
    """Plant periods of `period` s; sample k solved on the state of tick `ticks[k]` (ticks counted from the
    first sample's; the last entry: the recorded final state's, or sample_time's worth later);
    `offsets[k]`: s from that tick to the arrival of sample k's command (None: after the last recorded
    state); `arrivals`: every recorded command's arrival in order; `held`: the plant held its state
    until the first command (hold_until_command), else it moved under a zero command."""

    period: float
    ticks: list[int]
    offsets: list[float | None]
    arrivals: list[Arrival] = field(default_factory=list)
    held: bool = True
    #: s per sample: the delay its controller predicted from the state to the command's effect (diagnostics
    #: `predicted_delay_ms`; None: not recorded)
    predicted: np.ndarray | None = None

    def beyond_prediction(self) -> np.ndarray:
        """s each sample's command took effect after the instant its controller planned from (the fitted arrival
        minus `predicted`; > 0: later). What latency compensation cannot see: the commands' timing jitter.
        Empty without `predicted`."""
        if self.predicted is None:
            return np.zeros(0)
        return np.array([d - p for d, p in zip(self.offsets, self.predicted, strict=False) if d is not None])

    @property
    def steps(self) -> list[int]:
        """Plant periods between the state sample k solved on and the next one."""
        return [int(b - a) for a, b in zip(self.ticks[:-1], self.ticks[1:], strict=True)]

    @property
    def late(self) -> list[int]:
        """Whole plant periods after its state before each sample's command acted (the earlier plant's measure)."""
        return [int(math.floor(d / self.period + 1e-9)) if d is not None else s
                for d, s in zip(self.offsets, self.steps, strict=True)]

    @property
    def late_commands(self) -> int:
        """How many commands acted a plant step or more after their state (`late` not 0)."""
        return sum(1 for n in self.late if n)

    def describe(self) -> str:
        steps = self.steps
        between = steps[:-1] or steps  # the last: to the final state
        known = [d for d in self.offsets if d is not None]
        late = self.late_commands
        spread = (f"each command acting {min(known) * 1e3:.4g} to {max(known) * 1e3:.4g} ms (median "
                  f"{float(np.median(known)) * 1e3:.4g} ms) after the state its sample solved on" if known else
                  "no command seen acting")
        others = sum(1 for a in self.arrivals if a.sample is None)
        extra = (f", {others} other recorded command(s) (late cover, deactivation) replayed as recorded"
                 if others else "")
        beyond = self.beyond_prediction() * 1e3
        jitter = (f"; against the controller's prediction: {np.median(beyond):+.3g} ms at the median, "
                  f"{np.percentile(beyond, 90):+.3g} at p90, {beyond.max():+.3g} at most" if beyond.size else "")
        return (f"the recorded timing: plant steps of {self.period * 1e3:g} ms, {min(between)} to {max(between)} per "
                f"sample, {spread}{extra}, {late} of {len(self.offsets)} commands a plant step or more late{jitter}")


def _state_messages(bag: Bag) -> tuple[list[np.ndarray], list[int]]:
    """The recorded plant states (the `state` topic, namespaced or not) in order, and their log times (ns)."""
    name = next((t for t in sorted(bag.topics) if t == "/state" or t.endswith("/state")), None)
    msgs = bag.topics.get(name, []) if name else []
    return [np.asarray(msg.data, float) for _, msg in msgs], [int(t) for t, _ in msgs]


def _recorded_commands(bag: Bag, run: RecordedRun) -> list[tuple[int, np.ndarray, int | None]]:
    """Every command the plant got, in order: (log time ns, value, sample or None). From the recorded `command`
    topic where it holds each sample's command; else (bags without it) the samples' own, at their
    diagnostics' log times."""
    name = next((t for t in sorted(bag.topics) if t == "/command" or t.endswith("/command")), None)
    stamps = [t for t, _ in controller_samples(bag)[0]]
    own = [(stamps[k] if k < len(stamps) else 0, np.asarray(u, float), k) for k, u in enumerate(run.u)]
    if not name:
        return own
    try:
        msgs = [(int(t), np.asarray(msg.data, float)) for t, msg in bag.topics[name]]
    except AttributeError:  # not arrays (a robot's Twist): the samples' own
        return own
    out: list[tuple[int, np.ndarray, int | None]] = []
    k, start = 0, 0
    while k < len(run.u):
        i = next((i for i in range(start, len(msgs)) if msgs[i][1].shape == run.u[k].shape
                  and np.array_equal(msgs[i][1], run.u[k])), None)
        if i is None:
            return own
        out += [(t, u, None) for t, u in msgs[start:i]] + [(msgs[i][0], msgs[i][1], k)]
        k, start = k + 1, i + 1
    return out + [(t, u, None) for t, u in msgs[start:]]


def _period(plant: Plant, x: np.ndarray, pieces: list[tuple[np.ndarray | None, float]]) -> np.ndarray:
    """x [n] advanced over consecutive pieces (input [m] or None: held still, duration s), as the plant node does."""
    for u, dt in pieces:
        if u is not None and dt > 0:
            x = plant.advance(x, u, dt)
    return np.asarray(x, float)


def _pieces(in_force: np.ndarray | None, switches: list[tuple[float, np.ndarray]], period: float
            ) -> list[tuple[np.ndarray | None, float]]:
    """A period's pieces: `in_force` up to the first switch (s after the tick), each switch's input to the next,
    the last to the period's end; durations computed as the plant node computes them (upto - done)."""
    pieces, done, u = [], 0.0, in_force
    for s, value in switches:
        pieces.append((u, s - done))
        done, u = s, value
    pieces.append((u, period - done))
    return pieces


class _Fit:
    """Arrival times within one period: `s` [m] s after the tick, and how closely they reproduce its end state."""

    def __init__(self, plant: Plant, x: np.ndarray, target: np.ndarray, in_force: np.ndarray | None,
                 values: list[np.ndarray], period: float, guesses: list[float]) -> None:
        self.plant, self.x, self.target, self.in_force, self.values, self.period = \
            plant, x, target, in_force, values, period

        def residual(s: np.ndarray) -> np.ndarray:
            return self.end(np.sort(np.clip(s, 0.0, period))) - target

        guess = np.clip(np.array(guesses, float), 1e-12 * period, period * (1 - 1e-12))
        sol = least_squares(residual, guess, bounds=(0.0, period), method="trf", x_scale=period,
                            xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=60)
        s = np.sort(np.clip(sol.x, 0.0, period))
        error = self.error(s)
        for j in range(len(s)):  # the earlier plant's whole periods sit on the bounds: snap where no worse
            for bound in (0.0, period):  # (0 on a tie: a command that changes nothing acts at once)
                trial = s.copy()
                trial[j] = bound
                trial = np.sort(trial)
                if (e := self.error(trial)) < error or (e == error and bound == 0.0):
                    s, error = trial, e
        self.s, self.residual = s, error

    def end(self, s: np.ndarray) -> np.ndarray:
        return _period(self.plant, self.x, _pieces(self.in_force, list(zip(s, self.values, strict=True)), self.period))

    def error(self, s: np.ndarray) -> float:
        return float(np.max(np.abs(self.end(s) - self.target)))


def _solved_ticks(states: list[np.ndarray], run: RecordedRun) -> tuple[list[int] | None, str]:
    found: list[int] = []
    for k, x in enumerate(run.x):
        start = found[-1] if found else 0
        i = next((i for i in range(start, len(states)) if states[i].shape == x.shape and np.array_equal(states[i], x)),
                 None)
        if i is None:
            return None, f"sample {k}'s state is not among the recorded states"
        while k == 0 and i + 1 < len(states) and np.array_equal(states[i + 1], x):
            i += 1  # held x0: the plant moves from the last one
        found.append(i)
    return found, ""


def recorded_timing(bag: Bag, run: RecordedRun, plant: Plant, period: float, sample_time: float,
                    held: bool = True) -> tuple[RecordedTiming | None, str]:
    """The timing of `run` in `bag` (`plant`: the continuous plant, `period`: its step, s; `held`: it held x0 until
    the first command) and one line on it; (None, why) when the recorded states do not tell it (no array
    states, noise, another plant)."""
    states, state_ns = _state_messages(bag)
    found, why = _solved_ticks(states, run)
    if found is None:
        return None, why
    final = None
    if run.final_state is not None:
        final = next((i for i in range(found[-1] + 1, len(states)) if np.array_equal(states[i], run.final_state)),
                     None)
    last = final if final is not None else found[-1] + max(1, round(sample_time / period))
    commands = _recorded_commands(bag, run)
    # the earliest tick each command can arrive after: its sample's state (a command besides them: the last one's)
    earliest, sample_of = [], -1
    for _, _, k in commands:
        sample_of = k if k is not None else sample_of
        earliest.append(found[max(sample_of, 0)])

    def guess(j: int) -> tuple[int, float]:
        """Command j's arrival guessed from its log time: (period index, s after its tick)."""
        t = commands[j][0]
        i = max(earliest[j], bisect.bisect_right(state_ns, t) - 1)
        return i, min(max((t - state_ns[i]) * 1e-9, 0.0), period)

    guesses = [guess(j) for j in range(len(commands))]
    in_force: np.ndarray | None = None if held else np.zeros_like(run.u[0])
    placed: list[float] = []  # s after the first sample's tick, per command in order
    j = 0
    for i in range(found[0], min(last, len(states) - 1)):
        if j >= len(commands):
            break
        x, target = states[i], states[i + 1]
        none = float(np.max(np.abs(_period(plant, x, _pieces(in_force, [], period)) - target)))
        best: _Fit | None = None
        for m in range(1, min(MAX_ARRIVALS_PER_PERIOD, len(commands) - j) + 1):
            if earliest[j + m - 1] > i or (none <= FIT_TOLERANCE and guesses[j + m - 1][0] > i):
                break  # cannot have arrived yet, or nothing says it has
            start = [guesses[q][1] if guesses[q][0] == i else (0.0 if guesses[q][0] < i else period)
                     for q in range(j, j + m)]
            fit = _Fit(plant, x, target, in_force, [commands[q][1] for q in range(j, j + m)], period, start)
            if best is None or fit.residual < best.residual:
                best = fit
            if fit.residual <= FIT_TOLERANCE:
                break
        if best is not None and best.residual <= FIT_TOLERANCE:
            for s in best.s:
                if s >= period:  # fitted to the period's end: it acts from the next tick, fitted there
                    break
                placed.append((i - found[0]) * period + float(s))
                in_force = commands[j][1]
                j += 1
        elif none > FIT_TOLERANCE:
            residual = best.residual if best is not None else none
            return None, (f"the recorded state {i + 1} follows from state {i} under no arrival of the recorded "
                          f"commands within the plant's {period * 1e3:g} ms period (closest: {residual:.3g} off)")
    arrivals = [Arrival(at, commands[q][1], commands[q][2]) for q, at in enumerate(placed)]
    offsets: list[float | None] = [None] * len(run.u)
    for a in arrivals:
        if a.sample is not None:
            offsets[a.sample] = a.at - (found[a.sample] - found[0]) * period
    timing = RecordedTiming(period, [i - found[0] for i in found] + [last - found[0]], offsets, arrivals, held,
                            run.delays)
    error = reproduction_error(timing, plant, run, sample_time)
    if not error <= TIMING_TOLERANCE:
        return None, (f"the recorded commands with the plant's {period * 1e3:g} ms steps reproduce the recorded "
                      f"states only to {error:.3g}")
    return timing, timing.describe()


def reproduction_error(timing: RecordedTiming, plant: Plant, run: RecordedRun, sample_time: float) -> float:
    """max |x - x_recorded| over the samples' states (and the final one) when the recorded commands drive
    `plant` with `timing` from the first sample's state."""
    replayed = TimedPlant(plant, timing)
    x, error = run.x[0], 0.0
    for k, u in enumerate(run.u):
        x = replayed.advance(x, u, sample_time)
        reference = run.x[k + 1] if k + 1 < len(run.x) else run.final_state
        if reference is not None:
            error = max(error, float(np.max(np.abs(x - reference))))
    return error


class TimedPlant:
    """`plant` advanced as the recording's real-time plant was: sample k lasts `steps[k]` plant periods from the
    tick of its state; each recorded command acts from its arrival (a sample's: the command the replay gives
    for that sample; any other: its recorded value); before the first, the plant holds its state (`held`)."""

    def __init__(self, plant: Plant, timing: RecordedTiming) -> None:
        self.plant, self.timing = plant, timing
        self.sample = 0
        self.given: dict[int, np.ndarray] = {}
        self.next = 0  # the next arrival to apply
        self.in_force: np.ndarray | None = None

    def advance(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """State [n] after sample `self.sample` from x [n] under u [m] (dt, the nominal sample time, unused
        while the recording lasts; after it, the last sample's periods and u from its start)."""
        t, k = self.timing, self.sample
        self.given[k] = np.asarray(u, float)
        if self.in_force is None and not t.held:
            self.in_force = np.zeros_like(self.given[k])
        x = np.asarray(x, float)
        if k >= len(t.offsets):  # beyond the recording
            self.sample += 1
            self.in_force = self.given[k]
            return self.plant.advance(x, u, dt)
        for i in range(t.ticks[k], t.ticks[k + 1]):
            end = (i + 1) * t.period
            switches = []
            while self.next < len(t.arrivals) and t.arrivals[self.next].at < end:
                a = t.arrivals[self.next]
                value = a.value if a.sample is None else self.given.get(a.sample, a.value)
                switches.append((a.at - i * t.period, value))
                self.next += 1
            x = _period(self.plant, x, _pieces(self.in_force, switches, t.period))
            if switches:
                self.in_force = switches[-1][1]
        self.sample += 1
        return x
