"""Avoidance regions as values (paper section V): ellipses and convex polygons (rotated boxes), each a
set to stay OUT of with a function g that is positive inside and non-positive outside (`depth`), and
the parameter values of its NLP slot (`slot_values`; the layout and the symbolic g are
core/problem/regions.py).

Each region lies in a plane spanned by two coordinates of the state (`frame="state"`) or the
output (`frame="output"`); which coordinates is a setting of the controller (`plane`).

Moving regions: every region carries a velocity (plane units per second, in its own plane and
frame) and the time `stamp` (s) at which its pose was valid. Stage k of the horizon, at time
t_k = t_0 + k Ts, sees the region translated to c + v (t_k - stamp); the slot holds v and
stamp - t_0, so this is a parameter change and nothing is rebuilt. The rotation stays fixed over
the horizon (a yaw rate is not predicted). A static region (v = 0) gives exactly the same numbers
as a region without motion: its shift is an exact floating-point zero.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import RegionError

FRAMES = ("state", "output")
#: parameters per ellipse slot: active, in_state_frame, cx, cy, 1/a, 1/b, cos(yaw), sin(yaw),
#: then its motion: vx, vy, stamp - t_0
ELLIPSE_SLOT_SIZE = 11
#: index of the motion (vx, vy, stamp - t_0) in an ellipse slot
ELLIPSE_MOTION = 8
#: fixed parameters per polygon slot before the half-planes: active, in_state_frame, vx, vy, stamp - t_0
POLYGON_SLOT_HEADER = 5
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


def _motion(velocity: Sequence[float], stamp: float) -> tuple[tuple[float, float], float]:
    """Checked (velocity, stamp); a static region's stamp is 0.0, as its pose holds at all times."""
    vel = _finite("velocity", velocity)
    if len(vel) != 2:
        raise RegionError(f"velocity must have 2 components, got {vel}")
    try:
        t = float(stamp)
    except (TypeError, ValueError, OverflowError):
        raise RegionError(f"stamp must be a number of seconds, got {stamp!r}") from None
    if not math.isfinite(t):
        raise RegionError(f"stamp must be finite seconds, got {t}")
    if vel == (0.0, 0.0):
        return (0.0, 0.0), 0.0  # also turns -0.0 into 0.0, so equal regions compare equal
    return (vel[0], vel[1]), t


def _motion_values(region: Ellipse | Polygon, now: float | None, predict: bool) -> list[float]:
    """vx, vy, stamp - now of a slot; zeros when not predicting or the region is static."""
    if not predict or region.velocity == (0.0, 0.0):
        return [0.0, 0.0, 0.0]
    return [*region.velocity, 0.0 if now is None else region.stamp - float(now)]


class _Moving:
    """Motion shared by the region types: `velocity` (plane units/s) and `stamp` (s) of the pose."""

    velocity: tuple[float, float]
    stamp: float

    @property
    def moving(self) -> bool:
        return self.velocity != (0.0, 0.0)

    @property
    def reference_point(self) -> tuple[float, float]:
        """A point that moves with the region (ellipse centre, polygon vertex mean)."""
        raise NotImplementedError

    def offset_at(self, t: float) -> tuple[float, float]:
        """Translation of the pose from `stamp` to time t (s)."""
        dt = float(t) - self.stamp
        return self.velocity[0] * dt, self.velocity[1] * dt


@dataclass(frozen=True)
class Ellipse(_Moving):
    """Ellipse to avoid: centre (m or state units), semi-axes a, b (> 0), yaw (rad).

    `velocity` (units/s) moves the centre; `center` is the centre at time `stamp` (s).
    """

    center: tuple[float, float]
    semi_axes: tuple[float, float]
    yaw: float = 0.0
    frame: str = "state"
    velocity: tuple[float, float] = (0.0, 0.0)
    stamp: float = 0.0

    def __post_init__(self) -> None:
        center = _finite("ellipse centre", self.center)
        axes = _finite("ellipse semi-axes", self.semi_axes)
        (yaw,) = _finite("ellipse yaw", (self.yaw,))
        if len(center) != 2 or len(axes) != 2:
            raise RegionError("an ellipse needs a 2-d centre and 2 semi-axes")
        if min(axes) <= 1e-9:
            raise RegionError(f"ellipse semi-axes must be positive, got {axes}")
        _check_frame(self.frame)
        velocity, stamp = _motion(self.velocity, self.stamp)
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "semi_axes", axes)
        object.__setattr__(self, "yaw", yaw)
        object.__setattr__(self, "velocity", velocity)
        object.__setattr__(self, "stamp", stamp)

    def slot_values(self, now: float | None = None, predict: bool = True) -> np.ndarray:
        """Parameter vector of one ellipse slot (length ELLIPSE_SLOT_SIZE), active.

        `now`: time (s) of the sample's x(0); None places the pose at x(0)'s time. Without
        `predict` the motion is zero: the region stays where it was at `stamp`.
        """
        return np.array(
            [1.0, float(self.frame == "state"), *self.center, 1 / self.semi_axes[0], 1 / self.semi_axes[1],
             math.cos(self.yaw), math.sin(self.yaw), *_motion_values(self, now, predict)]
        )

    @property
    def reference_point(self) -> tuple[float, float]:
        return self.center

    def with_motion(self, velocity: Sequence[float], stamp: float) -> Ellipse:
        """The same ellipse moving at `velocity` (units/s), its pose valid at `stamp` (s)."""
        return dataclasses.replace(self, velocity=tuple(velocity), stamp=stamp)

    def at(self, t: float) -> Ellipse:
        """The ellipse at time t (s): centre moved by velocity * (t - stamp), same velocity."""
        dx, dy = self.offset_at(t)
        return dataclasses.replace(self, center=(self.center[0] + dx, self.center[1] + dy), stamp=float(t))

    def depth(self, point: Sequence[float]) -> float:
        """g at a point of the plane at time `stamp`: 1 - normalised squared radius (> 0 inside)."""
        return float(ellipse_g(np.asarray(point, float), self.slot_values()))

    def inflated(self, margin: float) -> Ellipse:
        """The ellipse with both semi-axes longer by `margin` (plane units, >= 0). A circle grows by exactly
        `margin`; an ellipse holds every point within `margin` of it along its axes and, in any direction,
        within (b / a) `margin` at least (b <= a its semi-axes; tight: 0.25 margin at a / b = 60, near the tips
        of a thin ellipse). The whole margin in every direction would take b' = sqrt(b^2 + 2 a margin + margin^2)."""
        return self if margin == 0 else dataclasses.replace(
            self, semi_axes=(self.semi_axes[0] + margin, self.semi_axes[1] + margin))


@dataclass(frozen=True)
class Polygon(_Moving):
    """Convex polygon to avoid, vertices in order (either orientation), at least 3.

    `velocity` (units/s) translates it; `vertices` are its corners at time `stamp` (s).
    """

    vertices: tuple[tuple[float, float], ...]
    frame: str = "state"
    velocity: tuple[float, float] = (0.0, 0.0)
    stamp: float = 0.0

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
        velocity, stamp = _motion(self.velocity, self.stamp)
        object.__setattr__(self, "vertices", tuple(verts))
        object.__setattr__(self, "velocity", velocity)
        object.__setattr__(self, "stamp", stamp)
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

    def slot_values(self, max_vertices: int, now: float | None = None, predict: bool = True) -> np.ndarray:
        """Parameter vector of one polygon slot; unused half-planes repeat the first one.

        `now` and `predict` as in `Ellipse.slot_values`.
        """
        planes = self.half_planes()
        if len(planes) > max_vertices:
            raise RegionError(f"polygon has {len(planes)} vertices, more than the capacity {max_vertices}")
        padded = np.vstack([planes, np.repeat(planes[:1], max_vertices - len(planes), axis=0)])
        return np.concatenate([[1.0, float(self.frame == "state"), *_motion_values(self, now, predict)],
                               padded.ravel()])

    @property
    def reference_point(self) -> tuple[float, float]:
        x, y = np.mean(np.asarray(self.vertices), axis=0)
        return float(x), float(y)

    def with_motion(self, velocity: Sequence[float], stamp: float) -> Polygon:
        """The same polygon moving at `velocity` (units/s), its vertices valid at `stamp` (s)."""
        return dataclasses.replace(self, velocity=tuple(velocity), stamp=stamp)

    def inflated(self, margin: float) -> Polygon:
        """The polygon with every edge moved outward by `margin` (plane units, >= 0; the corners mitred):
        it holds every point within `margin` of this one."""
        if margin == 0:
            return self
        normals = self.half_planes()[:, :2]
        before = np.roll(normals, 1, axis=0)  # the edge that ends at each vertex
        # vertex i lies on edges i-1 and i: moved to where both offset edges meet
        shift = margin * (before + normals) / (1.0 + np.einsum("ij,ij->i", before, normals))[:, None]
        return dataclasses.replace(self, vertices=tuple(map(tuple, np.asarray(self.vertices) + shift)))

    def at(self, t: float) -> Polygon:
        """The polygon at time t (s): translated by velocity * (t - stamp), same velocity."""
        dx, dy = self.offset_at(t)
        return dataclasses.replace(self, vertices=tuple((x + dx, y + dy) for x, y in self.vertices), stamp=float(t))

    def depth(self, point: Sequence[float]) -> float:
        """g at a point: distance to the nearest edge, positive inside."""
        planes = self.half_planes()
        return float(np.min(planes[:, 2] - planes[:, :2] @ np.asarray(point, float)))


def rotated_box(center: Sequence[float], size: Sequence[float], yaw: float = 0.0, frame: str = "state",
                velocity: Sequence[float] = (0.0, 0.0), stamp: float = 0.0) -> Polygon:
    """Rectangle of full side lengths `size` centred at `center` (at time `stamp`), rotated by `yaw` rad."""
    centre, sides, (yaw,) = _finite("box centre", center), _finite("box size", size), _finite("box yaw", (yaw,))
    if len(centre) != 2 or len(sides) != 2:
        raise RegionError(f"a box needs a 2-d centre and 2 sides, got {centre} and {sides}")
    (cx, cy), (sx, sy) = centre, sides
    if min(sx, sy) <= 1e-9:
        raise RegionError(f"box sides must be positive, got {(sx, sy)}")
    c, s = math.cos(yaw), math.sin(yaw)
    corners = [(-sx / 2, -sy / 2), (sx / 2, -sy / 2), (sx / 2, sy / 2), (-sx / 2, sy / 2)]
    return Polygon(tuple((cx + c * dx - s * dy, cy + s * dx + c * dy) for dx, dy in corners), frame,
                   tuple(velocity), stamp)


Region = Ellipse | Polygon


def ellipse_g(point, slot):
    """g of an ellipse slot at a 2-d point (numpy or CasADi), > 0 inside."""
    dx = point[0] - slot[2]
    dy = point[1] - slot[3]
    # rotate the offset into the ellipse's own axes
    ex = (slot[6] * dx + slot[7] * dy) * slot[4]
    ey = (-slot[7] * dx + slot[6] * dy) * slot[5]
    return 1 - ex**2 - ey**2
