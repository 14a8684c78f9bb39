"""Clearance in the plane's own units: the signed Euclidean distance from a point to a region's boundary.

A region's g (core/problem/regions.py) is what the controller penalises: for an ellipse 1 - normalised
r^2, dimensionless; a robot user reads metres. `signed_distance` is the Euclidean distance from a
point of the region's plane to the nearest point of its boundary, positive outside (the clearance),
negative inside (the depth), in the plane's units: metres where the plane is a robot's position.

Ellipse: the closest point by D. Eberly's robust bisection ("Distance from a Point to an Ellipse",
2013), exact to float precision; polygon: the nearest edge (inside) or segment (outside).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..core.problem.models import Model
from ..core.problem.regions import Ellipse, Polygon, Region


def plane_units(model: Model, frame: str, plane: Sequence[int]) -> str:
    """The unit of a region frame's plane ("m" for a robot's position), else a description of it."""
    units = model.units.get(frame)  # the model file's `units`
    names = model.state_names if frame == "state" else model.output_names
    if units is not None and units[plane[0]] == units[plane[1]]:
        return units[plane[0]]
    return f"{frame} units ({names[plane[0]]}, {names[plane[1]]})"


def _bisect_root(r0: float, z0: float, z1: float, g: float) -> float:
    n0 = r0 * z0
    s0, s1 = z1 - 1.0, (0.0 if g < 0 else math.hypot(n0, z1) - 1.0)
    s = 0.0
    for _ in range(1100):  # float bisection ends long before (s hits s0 or s1)
        s = 0.5 * (s0 + s1)
        if s in (s0, s1):
            break
        value = (n0 / (s + r0)) ** 2 + (z1 / (s + 1.0)) ** 2 - 1.0
        if value > 0:
            s0 = s
        elif value < 0:
            s1 = s
        else:
            break
    return s


def _ellipse_first_quadrant(e0: float, e1: float, y0: float, y1: float) -> float:
    """Distance from (y0, y1) >= 0 to the ellipse (x/e0)^2 + (y/e1)^2 = 1 with e0 >= e1 > 0 (Eberly)."""
    if y1 > 0:
        if y0 > 0:
            z0, z1 = y0 / e0, y1 / e1
            g = z0 * z0 + z1 * z1 - 1.0
            if g == 0:
                return 0.0
            r0 = (e0 / e1) ** 2
            s = _bisect_root(r0, z0, z1, g)
            return math.hypot(r0 * y0 / (s + r0) - y0, y1 / (s + 1.0) - y1)
        return abs(y1 - e1)
    numer, denom = e0 * y0, e0 * e0 - e1 * e1
    if numer < denom:
        ratio = numer / denom
        return math.hypot(e0 * ratio - y0, e1 * math.sqrt(max(0.0, 1.0 - ratio * ratio)))
    return abs(y0 - e0)


def ellipse_distance(region: Ellipse, point: Sequence[float]) -> float:
    """Signed distance (plane units, > 0 outside) from `point` to the ellipse at its `stamp`."""
    dx, dy = point[0] - region.center[0], point[1] - region.center[1]
    c, s = math.cos(region.yaw), math.sin(region.yaw)
    u, v = abs(c * dx + s * dy), abs(-s * dx + c * dy)
    a, b = region.semi_axes
    if a < b:
        a, b, u, v = b, a, v, u
    distance = _ellipse_first_quadrant(a, b, u, v)
    return -distance if (u / a) ** 2 + (v / b) ** 2 < 1.0 else distance


def polygon_distance(region: Polygon, point: Sequence[float]) -> float:
    """Signed distance (plane units, > 0 outside) from `point` to the polygon at its `stamp`."""
    depth = region.depth(point)
    if depth > 0:
        return -depth
    p = np.asarray(point, float)
    a = np.asarray(region.vertices, float)
    b = np.roll(a, -1, axis=0)
    edge = b - a
    along = np.clip(np.einsum("ij,ij->i", p - a, edge) / np.einsum("ij,ij->i", edge, edge), 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + along[:, None] * edge - p, axis=1)))


def signed_distance(region: Region, point: Sequence[float]) -> float:
    """Signed Euclidean distance from a point of the region's plane to its boundary (> 0 outside)."""
    if isinstance(region, Ellipse):
        return ellipse_distance(region, point)
    if isinstance(region, Polygon):
        return polygon_distance(region, point)
    raise TypeError(f"no distance for a {type(region).__name__}")


def nearest_region_distance(plane: Sequence[int], output_plane: Sequence[int], x: np.ndarray, y: np.ndarray,
                            regions: Sequence[Sequence[Region]]) -> np.ndarray:
    """The smallest signed distance to any region in force at each state [len(x)] (inf where there is none);
    regions[k] as in core/loop/metrics.region_values (moved to each state's time already)."""
    out = np.full(len(x), math.inf)
    for k in range(len(x)):
        for region in regions[min(k, len(regions) - 1)] if len(regions) else ():
            ix, source = (plane, x[k]) if region.frame == "state" else (output_plane, y[k])
            out[k] = min(out[k], signed_distance(region, (source[ix[0]], source[ix[1]])))
    return out
