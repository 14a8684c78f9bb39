"""The perception pipeline a node calls: a scan (or a grid window) and the robot's pose -> tracked regions.

    perception = Perception(PerceptionSettings())
    seen = perception.from_scan(ranges, geometry, Pose2D(x, y, yaw), stamp)   # InputError: refused
    for track_id, region in seen.regions: ...

Refused input raises InputError and changes nothing: the tracks and the last good regions
(`last`) stay as they were. Of the fitted regions the nearest `max_circles` circles and
`max_walls` wall segments are kept (the controller's slots are fixed: max_ellipses,
max_polygons), so the regions that matter first are the ones it gets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from ..problem.shapes import FRAMES, Ellipse, Polygon
from .fitting import CIRCLE, FitSettings, Fitted, fit_regions
from .grid import Grid
from .scan import Pose2D, ScanGeometry, scan_points
from .tracks import Tracker, TrackSettings


@dataclass(frozen=True)
class PerceptionSettings:
    """The pipeline's settings: fitting, tracking, how many regions of each kind, their frame."""

    fit: FitSettings = field(default_factory=FitSettings)
    tracks: TrackSettings = field(default_factory=TrackSettings)
    #: circles kept (nearest first): the controller's max_ellipses
    max_circles: int = 6
    #: wall segments kept (nearest first): the controller's max_polygons
    max_walls: int = 3
    #: the plane the regions are given in (the robot interface maps odom to `output`)
    frame: str = "output"
    #: the laser frame in base_link (m, rad)
    laser_offset: Pose2D = field(default_factory=Pose2D)
    #: grid: cells within this of the robot along the grid's axes are looked at, m
    half_window: float = 5.0
    #: grid: a cell at least this occupied (percent) is an obstacle (nav2 map_server's occupied_thresh 0.65)
    occupied_threshold: int = 65

    def __post_init__(self) -> None:
        if self.frame not in FRAMES:
            raise ConfigError(f"frame must be one of {FRAMES}, got {self.frame!r}")
        if self.max_circles < 0 or self.max_walls < 0:
            raise ConfigError("max_circles and max_walls must be >= 0")
        if not (math.isfinite(self.half_window) and self.half_window > 0):
            raise ConfigError(f"half_window must be a positive number of metres, got {self.half_window}")
        if not 1 <= self.occupied_threshold <= 100:
            raise ConfigError(f"occupied_threshold must be in 1..100 percent, got {self.occupied_threshold}")


@dataclass(frozen=True)
class Perceived:
    """What one scan or grid window gave: `regions` ((track id, region with velocity and stamp), ...), the
    points used, and the beams dropped as not finite or out of range (a grid: 0)."""

    regions: tuple[tuple[int, Ellipse | Polygon], ...]
    points: int
    not_finite: int = 0
    out_of_range: int = 0


class Perception:
    """Scans or grid windows -> tracked regions; one per source (the tracks are its own)."""

    def __init__(self, settings: PerceptionSettings | None = None) -> None:
        self.settings = settings or PerceptionSettings()
        self.tracker = Tracker(self.settings.tracks)
        self.last: Perceived | None = None

    def from_scan(self, ranges: np.ndarray, geometry: ScanGeometry, robot: Pose2D, stamp: float) -> Perceived:
        """The regions of a scan taken at `stamp` (s) with the robot (base_link) at `robot` in odom."""
        sensor = robot.compose(self.settings.laser_offset)
        points = scan_points(ranges, geometry, sensor)
        fitted = fit_regions(points.points, points.sensor, robot.position, self.settings.fit, self.settings.frame,
                             ordered=True, closed=geometry.full_turn, enough=self.enough)
        return self._track(fitted, stamp, len(points.points), points.not_finite, points.out_of_range)

    def from_grid(self, grid: Grid, robot: Pose2D, stamp: float) -> Perceived:
        """The regions of the grid's occupied cells around the robot at `robot` (odom) at `stamp` (s)."""
        s = self.settings
        points = grid.occupied_points(robot.position, s.half_window, s.occupied_threshold)
        # neighbouring cells (diagonals too) are one object, whatever the gap setting
        gap = max(s.fit.cluster_gap, 1.5 * grid.resolution)
        fitted = fit_regions(points, robot.position, robot.position, s.fit, s.frame, gap=gap, enough=self.enough,
                             surface=False)
        # the points are cell centres: grown by half a cell's diagonal, a region covers its cells whole
        half_cell = grid.resolution * math.sqrt(0.5)
        fitted = [f.inflated(half_cell) for f in fitted]
        return self._track(fitted, stamp, len(points))

    def _track(self, fitted: list[Fitted], stamp: float, points: int, not_finite: int = 0,
               out_of_range: int = 0) -> Perceived:
        kept = self.nearest(fitted)
        tracks = self.tracker.update(kept, float(stamp))
        self.last = Perceived(tuple((t.id, t.region) for t in tracks), points, not_finite, out_of_range)
        return self.last

    @property
    def enough(self) -> tuple[int, int]:
        """(circles, walls) kept: fitting stops once it has them nearer than every cluster left."""
        return self.settings.max_circles, self.settings.max_walls

    def nearest(self, fitted: list[Fitted]) -> list[Fitted]:
        """The nearest max_circles circles and max_walls wall segments of `fitted` (sorted nearest first)."""
        circles = [f for f in fitted if f.kind == CIRCLE][: self.settings.max_circles]
        walls = [f for f in fitted if f.kind != CIRCLE][: self.settings.max_walls]
        return circles + walls
