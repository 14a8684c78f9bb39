"""Velocities of obstacle regions from successive updates (any tracker, any rate).

A region that arrives again under the same key (a marker's ns and id) at a later stamp has moved
by (p - p_prev) over (stamp - stamp_prev): that is its raw velocity. The estimate is filtered
(exponential smoothing with weight SMOOTHING on the newest raw value; the first raw value is
taken as it is), and reset to zero, with a reason, when:

- the stamp does not increase (an out-of-order update, or the same stamp at another place);
- the apparent speed exceeds `max_speed`: a jump (a re-identified track, a teleported marker);
- the region moves but its stamp lies more than `max_stamp_skew` s from its receipt time: its
  predicted position would be off by speed * skew.

A velocity given explicitly by the tracker replaces the estimate; it is refused (InputError) when
it is not finite, faster than `max_speed`, or its stamp is skewed. Units: plane units and s.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Hashable, Sequence
from dataclasses import dataclass

from ..errors import InputError

#: weight of the newest raw velocity in the filtered estimate
SMOOTHING = 0.5


@dataclass(frozen=True)
class Track:
    """The last update of one key: its stamp (s), reference position and filtered velocity."""

    stamp: float
    position: tuple[float, float]
    velocity: tuple[float, float] = (0.0, 0.0)
    estimated: bool = False  # at least one raw velocity went into `velocity`


@dataclass(frozen=True)
class Estimate:
    """Velocity to use for an update, and why the estimate was reset (None if it was not)."""

    velocity: tuple[float, float]
    reset: str | None = None


def _pair(name: str, values: Sequence[float]) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in values)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name} must be 2 numbers, got {values!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise InputError(f"{name} contains NaN or infinite values: ({x}, {y})")
    return x, y


class VelocityEstimator:
    """Per-key velocity tracks. `update` never leaves a track in a state that a later update cannot use."""

    def __init__(self, max_speed: float = 3.0, max_stamp_skew: float = 2.0) -> None:
        for name, value in (("max_speed", max_speed), ("max_stamp_skew", max_stamp_skew)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a positive finite number, got {value!r}")
        self.max_speed = float(max_speed)
        self.max_stamp_skew = float(max_stamp_skew)
        self._tracks: dict[Hashable, Track] = {}

    def __len__(self) -> int:
        return len(self._tracks)

    def forget(self, key: Hashable | None = None) -> None:
        """Drop one track (a deleted region) or all of them (None)."""
        if key is None:
            self._tracks.clear()
        else:
            self._tracks.pop(key, None)

    def retain(self, keys: Collection[Hashable]) -> None:
        """Drop the tracks of every key not in `keys`."""
        for key in [k for k in self._tracks if k not in keys]:
            del self._tracks[key]

    def track(self, key: Hashable) -> Track | None:
        return self._tracks.get(key)

    def update(self, key: Hashable, position: Sequence[float], stamp: float, receipt: float,
               velocity: Sequence[float] | None = None) -> Estimate:
        """The velocity of `key` after an update at `position`, valid at `stamp`, received at `receipt` (s).

        `velocity` given: checked and used as is (InputError if refused; the track is unchanged then).
        """
        position = _pair("position", position)
        stamp, receipt = float(stamp), float(receipt)
        if not (math.isfinite(stamp) and math.isfinite(receipt)):
            raise InputError(f"stamp and receipt time must be finite, got {stamp}, {receipt}")
        skew = stamp - receipt
        if velocity is not None:
            given = _pair("velocity", velocity)
            speed = math.hypot(*given)
            if speed > self.max_speed:
                raise InputError(f"velocity {speed:.3g} exceeds max_obstacle_speed {self.max_speed:g}")
            if speed > 0 and abs(skew) > self.max_stamp_skew:
                raise InputError(f"stamp is {_skew_text(skew)} its receipt (limit {self.max_stamp_skew:g} s): "
                                 "a moving region cannot be placed in time")
            self._tracks[key] = Track(stamp, position, given, True)
            return Estimate(given)
        previous = self._tracks.get(key)
        fresh = Track(stamp, position)
        if previous is None:
            self._tracks[key] = fresh
            return Estimate((0.0, 0.0))
        dt = stamp - previous.stamp
        moved = math.hypot(position[0] - previous.position[0], position[1] - previous.position[1])
        if dt <= 0:
            if dt == 0 and moved == 0:  # the same pose again (a latched or repeated message)
                return Estimate(previous.velocity)
            self._tracks[key] = fresh
            return Estimate((0.0, 0.0), f"stamp went from {previous.stamp:.9g} to {stamp:.9g} s: "
                                        "velocity estimate reset")
        raw = ((position[0] - previous.position[0]) / dt, (position[1] - previous.position[1]) / dt)
        if moved / dt > self.max_speed:
            self._tracks[key] = fresh
            return Estimate((0.0, 0.0), f"jumped {moved:.3g} in {dt:.3g} s ({moved / dt:.3g}/s > max_obstacle_speed "
                                        f"{self.max_speed:g}): velocity estimate reset")
        if previous.estimated:
            raw = tuple(v + SMOOTHING * (r - v) for v, r in zip(previous.velocity, raw))
        if raw != (0.0, 0.0) and abs(skew) > self.max_stamp_skew:
            self._tracks[key] = fresh
            return Estimate((0.0, 0.0), f"stamp is {_skew_text(skew)} its receipt (limit {self.max_stamp_skew:g} s): "
                                        "velocity estimate reset")
        self._tracks[key] = Track(stamp, position, (float(raw[0]), float(raw[1])), True)
        return Estimate(self._tracks[key].velocity)


def _skew_text(skew: float) -> str:
    return f"{abs(skew):.3g} s {'ahead of' if skew > 0 else 'behind'}"
