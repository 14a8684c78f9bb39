"""Fitted regions over time -> stable ids and velocities, for the prediction the controller already has
(core/problem/shapes.py: a region carries its velocity and the stamp its pose is valid at).

Association is a minimum-cost assignment (`scipy.optimize.linear_sum_assignment`) between the tracks and
the new regions of the same kind: a circle's cost is the distance of the new centre from the track's
predicted one, a wall segment's how far the new segment's middle lies outside the track's box; gated
at `gate` + `max_speed` dt: a region nobody claims starts a new track with a new id, a track nobody
matched ends. A circle's velocity is the least-squares slope of its centre over its last `window`
observations, once it has that many; below `min_speed`, or with the centres further than
`max_residual` from a straight-line motion, it is static: the fit of a static object jitters or slides
as the robot's view of it changes (docs/design.md, 'Obstacles from sensors'). Wall segments are
static: the part of a wall a moving robot sees slides along it, and that is not motion.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..errors import ConfigError
from ..problem.shapes import Ellipse, Polygon
from .fitting import CIRCLE, Fitted

#: a cost that never wins an assignment (pairs beyond the gate)
_FORBIDDEN = 1e9


@dataclass(frozen=True)
class TrackSettings:
    """How regions are associated and their velocities estimated (m, s)."""

    #: the farthest a region may be from its track's predicted place and still be the same object, m
    gate: float = 0.5
    #: the fastest obstacle followed, m/s; a faster apparent motion starts a new track
    max_speed: float = 3.0
    #: observations the velocity is fitted over (>= 2)
    window: int = 5
    #: slower than this, m/s: static (velocity exactly 0, so the controller packs the region once)
    min_speed: float = 0.1
    #: the centres may leave the fitted straight-line motion by this much (RMS, m) and still be one moving
    #: object; more: static (the fit of a static object jumps as the robot's view of it changes)
    max_residual: float = 0.03

    def __post_init__(self) -> None:
        for name in ("gate", "max_speed"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")
        if self.window < 2 or not (math.isfinite(self.min_speed) and self.min_speed >= 0):
            raise ConfigError("window must be >= 2 and min_speed >= 0")
        if not (math.isfinite(self.max_residual) and self.max_residual > 0):
            raise ConfigError(f"max_residual must be positive, got {self.max_residual}")


@dataclass
class Track:
    """One object followed over time: `id`, its kind, its last region (motion included), and the
    (stamp s, x m, y m) of its last observations."""

    id: int
    kind: str
    region: Ellipse | Polygon
    history: deque = field(default_factory=deque)
    #: a wall segment's half-planes (nx, ny, b) [E, 3], by which the next scan's segments are matched to it
    planes: np.ndarray | None = None

    @property
    def velocity(self) -> tuple[float, float]:
        return self.region.velocity

    def predicted(self, stamp: float) -> np.ndarray:
        t, x, y = self.history[-1]
        vx, vy = self.velocity
        return np.array([x + vx * (stamp - t), y + vy * (stamp - t)])


class Tracker:
    """Tracks of fitted regions; `update` once per scan or grid window with its stamp (s)."""

    def __init__(self, settings: TrackSettings | None = None) -> None:
        self.settings = settings or TrackSettings()
        self.tracks: list[Track] = []
        self.next_id = 0
        self.last_stamp: float | None = None

    def reset(self) -> None:
        self.tracks = []
        self.last_stamp = None

    def update(self, fitted: list[Fitted], stamp: float) -> list[Track]:
        """Associate `fitted` (seen at `stamp`) with the tracks; returns the tracks seen now, in the order of
        `fitted`, each region with its velocity and `stamp`. A stamp older than the last one resets the tracks
        (a replayed or restarted source: old velocities would be nonsense)."""
        if self.last_stamp is not None and stamp < self.last_stamp:
            self.reset()
        dt = 0.0 if self.last_stamp is None else stamp - self.last_stamp
        matches = self._associate(fitted, stamp, dt)
        seen: list[Track] = []
        for i, item in enumerate(fitted):
            point = item.center
            track = matches.get(i)
            if track is None:
                track = Track(self.next_id, item.kind, item.region, deque(maxlen=self.settings.window))
                self.next_id += 1
            if track.history and track.history[-1][0] == stamp:
                track.history.pop()  # the same instant seen again: the newer fit replaces it
            track.history.append((stamp, *point))
            velocity = self._velocity(track)
            # a static region's pose holds at all times (its stamp is 0, core/problem/shapes.py): no copy
            track.region = item.region.with_motion(velocity, stamp) if velocity != (0.0, 0.0) else item.region
            track.planes = item.planes if item.kind != CIRCLE else None
            seen.append(track)
        self.tracks = seen
        self.last_stamp = stamp
        return seen

    def _associate(self, fitted: list[Fitted], stamp: float, dt: float) -> dict[int, Track]:
        """index in `fitted` -> its track (same kind, within the gate; the assignment of least total distance)."""
        if not self.tracks or not fitted:
            return {}
        reach = self.settings.gate + self.settings.max_speed * max(dt, 0.0)
        predicted = np.array([t.predicted(stamp) for t in self.tracks])
        points = np.array([f.center for f in fitted])
        cost = np.hypot(*(points[:, None, :] - predicted[None, :, :]).transpose(2, 0, 1))
        for j, track in enumerate(self.tracks):
            if track.planes is not None:
                # a wall segment: how far the new one's middle lies outside the old box (0 inside), as the
                # seen part of a wall slides along it when the robot or what stands in front moves
                cost[:, j] = np.maximum(np.max(points @ track.planes[:, :2].T - track.planes[:, 2], axis=1), 0.0)
        kinds_differ = np.array([f.kind for f in fitted])[:, None] != np.array([t.kind for t in self.tracks])[None, :]
        cost[kinds_differ | (cost > reach)] = _FORBIDDEN
        rows, cols = linear_sum_assignment(cost)
        return {int(r): self.tracks[c] for r, c in zip(rows, cols, strict=True) if cost[r, c] < _FORBIDDEN}

    def _velocity(self, track: Track) -> tuple[float, float]:
        """Least-squares slope of the reference point over the track's window, m/s (0 for walls and slow ones)."""
        if track.kind != CIRCLE or len(track.history) < self.settings.window:
            return (0.0, 0.0)  # a full window first: a new track's first fits are the least settled
        samples = np.asarray(track.history)
        times = samples[:, 0] - samples[:, 0].mean()
        spread = float(times @ times)
        if spread <= 0.0:
            return (0.0, 0.0)
        offsets = samples[:, 1:] - samples[:, 1:].mean(axis=0)
        vx, vy = (times @ offsets) / spread
        speed = math.hypot(vx, vy)
        # a walker moves along a line; a static object's fit jitters or slides as the view changes
        residual = math.sqrt(float(np.mean(np.sum((offsets - np.outer(times, (vx, vy))) ** 2, axis=1))))
        if speed < self.settings.min_speed or residual > self.settings.max_residual:
            return (0.0, 0.0)
        if speed > self.settings.max_speed:
            # faster than anything followed: two objects confused, or a jump; start the estimate again
            track.history = deque([track.history[-1]], maxlen=self.settings.window)
            return (0.0, 0.0)
        return (float(vx), float(vy))
