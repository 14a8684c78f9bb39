"""A planar lidar simulated against line segments and circles (vectorised numpy): the synthetic scans of
the tests and the benchmark, and a start for a simulator's lidar."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .scan import Pose2D


def cast(sensor: Pose2D, angles: np.ndarray, segments: Sequence[tuple[float, float, float, float]] = (),
         circles: Sequence[tuple[float, float, float]] = (), range_max: float = 30.0) -> np.ndarray:
    """Ranges (m) [B] of beams at `angles` [B] (rad, in the sensor frame) from `sensor` (odom) to the nearest
    segment (x0, y0, x1, y1) or circle (cx, cy, r), in odom; inf where nothing is within `range_max`."""
    heading = sensor.yaw + np.asarray(angles, float)
    d = np.column_stack([np.cos(heading), np.sin(heading)])  # [B, 2] unit directions
    origin = sensor.position
    best = np.full(len(d), np.inf)
    if len(segments):
        seg = np.asarray(segments, float)
        a, e = seg[:, :2] - origin, seg[:, 2:] - seg[:, :2]  # [S, 2]: start from the sensor, edge
        # origin + t d = start + s e  ->  t d - s e = a, solved by Cramer's rule for every (beam, segment)
        det = -d[:, None, 0] * e[None, :, 1] + d[:, None, 1] * e[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (-a[None, :, 0] * e[None, :, 1] + a[None, :, 1] * e[None, :, 0]) / det
            s = (d[:, None, 0] * a[None, :, 1] - d[:, None, 1] * a[None, :, 0]) / det
        hit = (np.abs(det) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1)
        best = np.minimum(best, np.where(hit, t, np.inf).min(axis=1))
    for cx, cy, r in circles:
        offset = origin - np.array([cx, cy])
        b = d @ offset
        disc = b * b - (offset @ offset - r * r)
        with np.errstate(invalid="ignore"):
            t = -b - np.sqrt(disc)
        best = np.minimum(best, np.where((disc >= 0) & (t > 0), t, np.inf))
    return np.where(best <= range_max, best, np.inf)


def room(half_x: float, half_y: float, center: Sequence[float] = (0.0, 0.0)) -> list[tuple[float, float, float, float]]:
    """The four inner faces of a rectangular room (m) as segments."""
    cx, cy = center
    corners = [(cx - half_x, cy - half_y), (cx + half_x, cy - half_y), (cx + half_x, cy + half_y),
               (cx - half_x, cy + half_y)]
    return [(*corners[i], *corners[(i + 1) % 4]) for i in range(4)]
