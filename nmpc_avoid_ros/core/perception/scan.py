"""A planar laser scan -> checked, cleaned points in `odom` (sensor_msgs/LaserScan's fields, no message).

A scan whose geometry is wrong (an angle increment of 0 or one that does not match the angle range
and the beam count, range limits that are not 0 < range_min < range_max, far too many beams) is
refused with an `InputError` naming the field: no point of it can be placed. Beams without a
usable return are cleaned: NaN and +-inf (REP 117: no return, or too close) and ranges outside
[range_min, range_max] are dropped and counted.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

#: more beams than this is not a planar lidar (the densest sold give a few 10k per turn): refused
#: before any per-beam work, so a bad message cannot stall the node
MAX_BEAMS = 100_000
#: beam count vs. angle range: drivers disagree whether angle_max is the last beam's angle or one
#: increment past it (a full turn), so one beam either way is accepted
COUNT_TOLERANCE = 1


@dataclass(frozen=True)
class Pose2D:
    """A planar pose: position (m) and yaw (rad) of a frame in its parent."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.x, self.y, self.yaw)):
            raise InputError(f"a pose must be finite, got ({self.x}, {self.y}, {self.yaw})")

    def compose(self, child: Pose2D) -> Pose2D:
        """The pose of `child` (given in this pose's frame) in this pose's parent."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose2D(self.x + c * child.x - s * child.y, self.y + s * child.x + c * child.y, self.yaw + child.yaw)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Points [K, 2] in this frame -> in the parent frame [K, 2]."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        rotation = np.array([[c, -s], [s, c]])
        return points @ rotation.T + np.array([self.x, self.y])

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x, self.y])

    def moved(self, speed: float, yaw_rate: float, dt: float) -> Pose2D:
        """The pose after `dt` s (negative: before) at `speed` (m/s, forward) and `yaw_rate` (rad/s), both
        constant: the exact arc, so that a scan is placed where the robot was when it was taken."""
        turn = yaw_rate * dt
        if abs(turn) < 1e-9:
            step, heading = speed * dt, self.yaw
        else:  # the chord of the arc, along the mean heading
            step, heading = 2.0 * speed / yaw_rate * math.sin(turn / 2.0), self.yaw + turn / 2.0
        return Pose2D(self.x + step * math.cos(heading), self.y + step * math.sin(heading), self.yaw + turn)


@dataclass(frozen=True)
class ScanGeometry:
    """The fields of a LaserScan that place its beams: angles (rad) and range limits (m)."""

    angle_min: float
    angle_max: float
    angle_increment: float
    range_min: float
    range_max: float

    @property
    def full_turn(self) -> bool:
        """The beams sweep a whole turn: the last one neighbours the first."""
        return abs(self.angle_max - self.angle_min) + 1.5 * abs(self.angle_increment) >= 2 * math.pi

    def check(self, beams: int) -> None:
        """InputError with the reason if `beams` ranges cannot be placed with this geometry."""
        if beams > MAX_BEAMS:
            raise InputError(f"scan has {beams} beams, more than {MAX_BEAMS}: refused")
        values = (self.angle_min, self.angle_max, self.angle_increment, self.range_min, self.range_max)
        if not all(math.isfinite(v) for v in values):
            raise InputError(f"scan angles and range limits must be finite, got {values}")
        if not self.range_min > 0.0:
            raise InputError(f"scan range_min must be > 0 m (a zero reading would be a return at the "
                             f"sensor), got {self.range_min}")
        if not self.range_max > self.range_min:
            raise InputError(f"scan range_max must exceed range_min, got {self.range_max} <= {self.range_min}")
        if self.angle_increment == 0.0 or abs(self.angle_increment) < 1e-9:
            raise InputError(f"scan angle_increment must be non-zero, got {self.angle_increment}")
        span = self.angle_max - self.angle_min
        expected = span / self.angle_increment + 1.0
        if expected < 0.5 or abs(beams - expected) > COUNT_TOLERANCE + 1e-6:
            raise InputError(f"scan has {beams} ranges, but angle_min {self.angle_min:.6g}, angle_max "
                             f"{self.angle_max:.6g} and angle_increment {self.angle_increment:.6g} give "
                             f"{expected:.1f} beams")
        if abs(self.angle_increment) * (beams - 1) > 2 * math.pi + abs(self.angle_increment):
            raise InputError(f"scan covers {abs(self.angle_increment) * (beams - 1):.3f} rad, more than a turn")


@dataclass(frozen=True)
class ScanPoints:
    """The usable returns of one scan: `points` [K, 2] (m, odom, in beam order), `sensor` the laser's
    position (m, odom), and the beams dropped: `not_finite` (NaN, +-inf), `out_of_range`."""

    points: np.ndarray
    sensor: np.ndarray
    not_finite: int
    out_of_range: int


def scan_points(ranges: Sequence[float] | np.ndarray, geometry: ScanGeometry, sensor_pose: Pose2D) -> ScanPoints:
    """Ranges (m, one per beam) of a scan taken at `sensor_pose` (the laser frame in odom) -> its points.

    Raises InputError (nothing placed) when the geometry does not fit the ranges (ScanGeometry.check).
    """
    values = np.asarray(ranges, dtype=float).ravel()
    geometry.check(values.size)
    finite = np.isfinite(values)
    in_range = finite & (values >= geometry.range_min) & (values <= geometry.range_max)
    index = np.flatnonzero(in_range)
    angles = geometry.angle_min + geometry.angle_increment * index
    r = values[index]
    local = np.column_stack([r * np.cos(angles), r * np.sin(angles)])
    return ScanPoints(sensor_pose.apply(local), sensor_pose.position, int(values.size - finite.sum()),
                      int(finite.sum() - in_range.sum()))
