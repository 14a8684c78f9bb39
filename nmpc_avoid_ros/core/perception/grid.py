"""An occupancy grid (nav_msgs/OccupancyGrid's fields, no message) -> occupied cell centres (m, odom) in a
square window around the robot.

Cells are row-major from the grid's origin (the pose of cell (0, 0)'s outer corner), x along a row;
values 0..100 are occupancy in percent, -1 unknown (not an obstacle here: the robot's own sensors see
what the map does not know). A grid whose resolution, size or data do not fit together is refused
with an `InputError` naming the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .scan import Pose2D

#: cells per grid at most (a 10 km square at 5 cm): larger is refused before its data is touched
MAX_CELLS = 400_000_000
#: the finest and coarsest resolution accepted, m per cell
RESOLUTION_RANGE = (1e-3, 100.0)


@dataclass(frozen=True)
class Grid:
    """A checked occupancy grid: `cells` [height, width] int8 (percent, -1 unknown), `resolution` (m per
    cell), `origin` (the pose of the grid's corner in odom)."""

    cells: np.ndarray
    resolution: float
    origin: Pose2D

    @classmethod
    def from_fields(cls, data: object, width: int, height: int, resolution: float, origin: Pose2D) -> Grid:
        """The grid of an OccupancyGrid's fields; InputError with the reason if they do not fit together."""
        low, high = RESOLUTION_RANGE
        if not (math.isfinite(resolution) and low <= resolution <= high):
            raise InputError(f"grid resolution must be in [{low:g}, {high:g}] m per cell, got {resolution}")
        if width <= 0 or height <= 0 or width * height > MAX_CELLS:
            raise InputError(f"grid size must be positive and at most {MAX_CELLS} cells, got {width} x {height}")
        cells = np.asarray(data, dtype=np.int8).ravel() if not isinstance(data, np.ndarray) else data.ravel()
        if cells.size != width * height:
            raise InputError(f"grid data has {cells.size} cells, but width x height is {width} x {height} = "
                             f"{width * height}")
        return cls(cells.reshape(height, width), float(resolution), origin)

    def occupied_points(self, robot: np.ndarray, half_window: float, threshold: int) -> np.ndarray:
        """Centres [K, 2] (m, odom) of the cells >= `threshold` percent whose cell lies within `half_window` (m)
        of the robot [2] along the grid's axes."""
        local = Pose2D(0.0, 0.0, -self.origin.yaw).apply((np.asarray(robot, float) - self.origin.position)[None])[0]
        col, row = np.floor(local / self.resolution).astype(int)
        reach = int(math.ceil(half_window / self.resolution))
        height, width = self.cells.shape
        rows = slice(max(row - reach, 0), max(min(row + reach + 1, height), 0))
        cols = slice(max(col - reach, 0), max(min(col + reach + 1, width), 0))
        r, c = np.nonzero(self.cells[rows, cols] >= threshold)
        centres = np.column_stack([c + cols.start + 0.5, r + rows.start + 0.5]) * self.resolution
        return self.origin.apply(centres)
