"""Avoidance regions and their penalty F (paper section V).

Every region is a set to stay OUT of, described by a function g that is positive inside the
region and non-positive outside; the penalty is F = max(0, g)^2, zero exactly outside.

Regions that arrive at run time (ellipses, rotated boxes, convex polygons) live in fixed-capacity
parameter slots of the NLP with an active flag, so changing them never rebuilds the problem.
Each region lies in a plane spanned by two coordinates of the state (`frame="state"`) or the
output (`frame="output"`); which coordinates is a setting of the controller (`plane`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .errors import RegionError

FRAMES = ("state", "output")
#: parameters per ellipse slot: active, in_state_frame, cx, cy, 1/a, 1/b, cos(yaw), sin(yaw)
ELLIPSE_SLOT_SIZE = 8
#: fixed parameters per polygon slot before the half-planes: active, in_state_frame
POLYGON_SLOT_HEADER = 2
MAX_COORDINATE = 1e6


def _finite(name: str, values: Sequence[float]) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int beyond float range
        raise RegionError(f"{name} must be numbers, got {values!r}") from None
    if not all(math.isfinite(v) and abs(v) <= MAX_COORDINATE for v in out):
        raise RegionError(f"{name} must be finite and within +-{MAX_COORDINATE:g}, got {out}")
    return out


def _check_frame(frame: str) -> None:
    if frame not in FRAMES:
        raise RegionError(f"frame must be one of {FRAMES}, got {frame!r}")


@dataclass(frozen=True)
class Ellipse:
    """Ellipse to avoid: centre (m or state units), semi-axes a, b (> 0), yaw (rad)."""

    center: tuple[float, float]
    semi_axes: tuple[float, float]
    yaw: float = 0.0
    frame: str = "state"

    def __post_init__(self) -> None:
        center = _finite("ellipse centre", self.center)
        axes = _finite("ellipse semi-axes", self.semi_axes)
        (yaw,) = _finite("ellipse yaw", (self.yaw,))
        if len(center) != 2 or len(axes) != 2:
            raise RegionError("an ellipse needs a 2-d centre and 2 semi-axes")
        if min(axes) <= 1e-9:
            raise RegionError(f"ellipse semi-axes must be positive, got {axes}")
        _check_frame(self.frame)
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "semi_axes", axes)
        object.__setattr__(self, "yaw", yaw)

    def slot_values(self) -> np.ndarray:
        """Parameter vector of one ellipse slot (length ELLIPSE_SLOT_SIZE), active."""
        return np.array(
            [1.0, float(self.frame == "state"), *self.center, 1 / self.semi_axes[0], 1 / self.semi_axes[1],
             math.cos(self.yaw), math.sin(self.yaw)]
        )

    def depth(self, point: Sequence[float]) -> float:
        """g at a point of the plane: 1 - normalised squared radius (> 0 inside)."""
        return float(ellipse_g(np.asarray(point, float), self.slot_values()))


@dataclass(frozen=True)
class Polygon:
    """Convex polygon to avoid, vertices in order (either orientation), at least 3."""

    vertices: tuple[tuple[float, float], ...]
    frame: str = "state"

    def __post_init__(self) -> None:
        try:
            raw = list(self.vertices)
        except TypeError:
            raise RegionError(f"polygon vertices must be a sequence of 2-d points, got {self.vertices!r}") from None
        verts = []
        for v in raw:
            pt = _finite("polygon vertex", v)
            if len(pt) != 2:
                raise RegionError(f"polygon vertices must be 2-d points, got {v!r}")
            verts.append(pt)
        # a closed LINE_STRIP repeats its first point: drop it
        if len(verts) > 1 and np.allclose(verts[0], verts[-1]):
            verts.pop()
        if len(verts) < 3:
            raise RegionError(f"a polygon needs at least 3 distinct vertices, got {len(verts)}")
        _check_frame(self.frame)
        object.__setattr__(self, "vertices", tuple(verts))
        self.half_planes()  # validates convexity and non-degeneracy

    def half_planes(self) -> np.ndarray:
        """Rows (nx, ny, b) with unit outward normals: inside iff n . p < b for every row."""
        pts = np.asarray(self.vertices)
        edges = np.roll(pts, -1, axis=0) - pts
        cross = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
        lengths = np.hypot(edges[:, 0], edges[:, 1])
        if np.any(lengths < 1e-9):
            raise RegionError("polygon has repeated consecutive vertices")
        if not (np.all(cross > 1e-12) or np.all(cross < -1e-12)):
            raise RegionError("polygon must be convex with vertices in order (split a non-convex one)")
        # every turn has the same sign, but a star (pentagram) or a doubly wound outline also does:
        # a simple convex polygon turns exactly once in total
        turning = np.sum(np.arctan2(cross, np.einsum("ij,ij->i", edges, np.roll(edges, -1, axis=0))))
        if abs(turning) > 3 * math.pi:
            raise RegionError("polygon must be simple: its outline crosses itself or winds more than once")
        orientation = 1.0 if cross[0] > 0 else -1.0
        # outward normal of a counter-clockwise edge (ex, ey) is (ey, -ex)
        normals = orientation * np.column_stack([edges[:, 1], -edges[:, 0]]) / lengths[:, None]
        offsets = np.einsum("ij,ij->i", normals, pts)
        return np.column_stack([normals, offsets])

    def slot_values(self, max_vertices: int) -> np.ndarray:
        """Parameter vector of one polygon slot; unused half-planes repeat the first one."""
        planes = self.half_planes()
        if len(planes) > max_vertices:
            raise RegionError(f"polygon has {len(planes)} vertices, more than the capacity {max_vertices}")
        padded = np.vstack([planes, np.repeat(planes[:1], max_vertices - len(planes), axis=0)])
        return np.concatenate([[1.0, float(self.frame == "state")], padded.ravel()])

    def depth(self, point: Sequence[float]) -> float:
        """g at a point: distance to the nearest edge, positive inside."""
        planes = self.half_planes()
        return float(np.min(planes[:, 2] - planes[:, :2] @ np.asarray(point, float)))


def rotated_box(center: Sequence[float], size: Sequence[float], yaw: float = 0.0, frame: str = "state") -> Polygon:
    """Rectangle of full side lengths `size` centred at `center`, rotated by `yaw` rad."""
    centre, sides, (yaw,) = _finite("box centre", center), _finite("box size", size), _finite("box yaw", (yaw,))
    if len(centre) != 2 or len(sides) != 2:
        raise RegionError(f"a box needs a 2-d centre and 2 sides, got {centre} and {sides}")
    (cx, cy), (sx, sy) = centre, sides
    if min(sx, sy) <= 1e-9:
        raise RegionError(f"box sides must be positive, got {(sx, sy)}")
    c, s = math.cos(yaw), math.sin(yaw)
    corners = [(-sx / 2, -sy / 2), (sx / 2, -sy / 2), (sx / 2, sy / 2), (-sx / 2, sy / 2)]
    return Polygon(tuple((cx + c * dx - s * dy, cy + s * dx + c * dy) for dx, dy in corners), frame)


Region = Ellipse | Polygon


def polygon_slot_size(max_vertices: int) -> int:
    return POLYGON_SLOT_HEADER + 3 * max_vertices


def ellipse_g(point, slot):
    """g of an ellipse slot at a 2-d point (numpy or CasADi), > 0 inside."""
    dx = point[0] - slot[2]
    dy = point[1] - slot[3]
    # rotate the offset into the ellipse's own axes
    ex = (slot[6] * dx + slot[7] * dy) * slot[4]
    ey = (-slot[7] * dx + slot[6] * dy) * slot[5]
    return 1 - ex**2 - ey**2


def _plane_point(state_point, output_point, slot):
    """The slot's point: its frame flag picks the state-plane or the output-plane point."""
    return state_point if output_point is None else slot[1] * state_point + (1 - slot[1]) * output_point


def ellipse_depth(state_point: ca.MX, output_point: ca.MX | None, slot: ca.MX) -> ca.MX:
    """active * g of one ellipse slot; its penalty F is max(0, active * g)^2."""
    return slot[0] * ellipse_g(_plane_point(state_point, output_point, slot), slot)


def polygon_depth(state_point: ca.MX, output_point: ca.MX | None, slot: ca.MX, max_vertices: int) -> ca.MX:
    """active * depth of one polygon slot, depth = min over edges of b - n . p (> 0 inside)."""
    point = _plane_point(state_point, output_point, slot)
    depth = None
    for k in range(max_vertices):
        row = POLYGON_SLOT_HEADER + 3 * k
        d = slot[row + 2] - slot[row] * point[0] - slot[row + 1] * point[1]
        depth = d if depth is None else ca.fmin(depth, d)
    return slot[0] * depth


@dataclass(frozen=True)
class SlotLayout:
    """Capacity of the obstacle parameter slots of one NLP structure."""

    max_ellipses: int = 8
    max_polygons: int = 4
    max_polygon_vertices: int = 8

    def __post_init__(self) -> None:
        for name, least in (("max_ellipses", 0), ("max_polygons", 0), ("max_polygon_vertices", 3)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < least:
                raise RegionError(f"{name} must be an integer >= {least}, got {value!r}")

    @property
    def size(self) -> int:
        return self.max_ellipses * ELLIPSE_SLOT_SIZE + self.max_polygons * polygon_slot_size(self.max_polygon_vertices)

    def pack(self, regions: Sequence[Region], output_frame_available: bool = True) -> np.ndarray:
        """All regions -> the flat slot parameter vector (inactive slots are zeros).

        Raises RegionError when there are more regions of a kind than slots, or a region uses the
        output frame on a model whose output has fewer than two coordinates.
        """
        if not isinstance(regions, Sequence) or isinstance(regions, str):
            raise RegionError(f"regions must be a sequence of Ellipse/Polygon, got {type(regions).__name__}")
        ellipses = [r for r in regions if isinstance(r, Ellipse)]
        polygons = [r for r in regions if isinstance(r, Polygon)]
        if len(ellipses) + len(polygons) != len(regions):
            raise RegionError("regions must be Ellipse or Polygon instances")
        if len(ellipses) > self.max_ellipses:
            raise RegionError(f"{len(ellipses)} ellipses exceed the capacity of {self.max_ellipses}")
        if len(polygons) > self.max_polygons:
            raise RegionError(f"{len(polygons)} polygons/boxes exceed the capacity of {self.max_polygons}")
        if not output_frame_available and any(r.frame == "output" for r in regions):
            raise RegionError("this model's output has fewer than 2 coordinates: use frame 'state'")
        values = np.zeros(self.size)
        for i, e in enumerate(ellipses):
            values[i * ELLIPSE_SLOT_SIZE:(i + 1) * ELLIPSE_SLOT_SIZE] = e.slot_values()
        base = self.max_ellipses * ELLIPSE_SLOT_SIZE
        width = polygon_slot_size(self.max_polygon_vertices)
        for i, poly in enumerate(polygons):
            values[base + i * width: base + (i + 1) * width] = poly.slot_values(self.max_polygon_vertices)
        return values

    def depths(self, slots: ca.MX, state_point: ca.MX, output_point: ca.MX | None) -> ca.MX:
        """active * g of every slot at one point [n_slots]; the penalty F is sum max(0, .)^2."""
        terms = [ellipse_depth(state_point, output_point, slots[i * ELLIPSE_SLOT_SIZE:(i + 1) * ELLIPSE_SLOT_SIZE])
                 for i in range(self.max_ellipses)]
        base = self.max_ellipses * ELLIPSE_SLOT_SIZE
        width = polygon_slot_size(self.max_polygon_vertices)
        for i in range(self.max_polygons):
            slot = slots[base + i * width: base + (i + 1) * width]
            terms.append(polygon_depth(state_point, output_point, slot, self.max_polygon_vertices))
        return ca.vertcat(*terms)
