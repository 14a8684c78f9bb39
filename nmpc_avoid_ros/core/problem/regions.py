"""Avoidance regions and their penalty F (paper section V).

Every region is a set to stay OUT of, described by a function g that is positive inside the
region and non-positive outside; the penalty is F = max(0, g)^2, zero exactly outside.

Regions that arrive at run time (ellipses, rotated boxes, convex polygons; core/problem/shapes.py,
whose names this module also exports) live in fixed-capacity parameter slots of the NLP with an
active flag, so changing them never rebuilds the problem: `SlotLayout` packs them, and g of a slot
at a point is written here symbolically (ellipse_depth, polygon_depth, ellipse_chord_sq). A moving
region's slot holds its velocity and stamp - t_0: stage k sees it translated to its time
(core/problem/shapes.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import RegionError
from .shapes import (
    ELLIPSE_MOTION,
    ELLIPSE_SLOT_SIZE,
    FRAMES,
    MAX_COORDINATE,
    POLYGON_SLOT_HEADER,
    Ellipse,
    Polygon,
    Region,
    ellipse_g,
    rotated_box,
)

#: the region values' names, exported here as before the split (core/problem/shapes.py)
__all__ = ["ELLIPSE_MOTION", "ELLIPSE_SLOT_SIZE", "FRAMES", "MAX_COORDINATE", "POLYGON_SLOT_HEADER", "Ellipse",
           "Polygon", "Region", "RegionError", "SlotLayout", "ellipse_chord_sq", "ellipse_depth", "ellipse_g",
           "polygon_depth", "polygon_slot_size", "rotated_box"]


def polygon_slot_size(max_vertices: int) -> int:
    return POLYGON_SLOT_HEADER + 3 * max_vertices


def _plane_point(state_point, output_point, slot):
    """The slot's point: its frame flag picks the state-plane or the output-plane point."""
    return state_point if output_point is None else slot[1] * state_point + (1 - slot[1]) * output_point


def _relative_point(point, velocity, stamp, elapsed: float):
    """The point in the region's frame at the stage time: p - v (t_k - stamp), t_k - t_0 = `elapsed`.

    Moving the point against the motion is the same as moving the region; for v = 0 the shift is
    an exact zero, so a static region gives the same numbers as before motion existed.
    """
    dt = elapsed - stamp
    return ca.vertcat(point[0] - velocity[0] * dt, point[1] - velocity[1] * dt)


def ellipse_depth(state_point: ca.MX, output_point: ca.MX | None, slot: ca.MX, elapsed: float = 0.0) -> ca.MX:
    """active * g of one ellipse slot at the stage `elapsed` s after x(0); penalty max(0, active * g)^2."""
    motion = ELLIPSE_MOTION
    point = _relative_point(_plane_point(state_point, output_point, slot), slot[motion:motion + 2],
                            slot[motion + 2], elapsed)
    return slot[0] * ellipse_g(point, slot)


def ellipse_chord_sq(a_state: ca.SX, a_output: ca.SX | None, b_state: ca.SX, b_output: ca.SX | None, slot: ca.SX,
                     elapsed_a: float, elapsed_b: float) -> ca.SX:
    """active * c^2 of one ellipse slot: c the length of the chord from a (at `elapsed_a` s after x(0)) to b,
    measured in the ellipse's own normalised coordinates (where it is the unit disk). g is a concave quadratic
    there, so along the chord g <= (1 - t) g(a) + t g(b) + t (1 - t) c^2 (core/nlp/between.py uses it)."""
    motion = ELLIPSE_MOTION
    a = _relative_point(_plane_point(a_state, a_output, slot), slot[motion:motion + 2], slot[motion + 2], elapsed_a)
    b = _relative_point(_plane_point(b_state, b_output, slot), slot[motion:motion + 2], slot[motion + 2], elapsed_b)
    dx, dy = b[0] - a[0], b[1] - a[1]
    ex = (slot[6] * dx + slot[7] * dy) * slot[4]
    ey = (-slot[7] * dx + slot[6] * dy) * slot[5]
    return slot[0] * (ex**2 + ey**2)


def polygon_depth(state_point: ca.MX, output_point: ca.MX | None, slot: ca.MX, max_vertices: int,
                  elapsed: float = 0.0) -> ca.MX:
    """active * depth of one polygon slot, depth = min over edges of b - n . p (> 0 inside), at the stage `elapsed`."""
    point = _relative_point(_plane_point(state_point, output_point, slot), slot[2:4], slot[4], elapsed)
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

    @property
    def time_offsets(self) -> np.ndarray:
        """Where each slot's stamp - t_0 sits in the slot vector: the one entry a region set's slots change by as
        time passes (a moving region's position is predicted from it; core/sample/feedback.py follows these)."""
        ellipses = np.arange(self.max_ellipses) * ELLIPSE_SLOT_SIZE + ELLIPSE_MOTION + 2
        width = polygon_slot_size(self.max_polygon_vertices)
        polygons = self.max_ellipses * ELLIPSE_SLOT_SIZE + np.arange(self.max_polygons) * width + \
            POLYGON_SLOT_HEADER - 1
        return np.concatenate([ellipses, polygons]).astype(int)

    def pack(self, regions: Sequence[Region], output_frame_available: bool = True, now: float | None = None,
             predict: bool = True) -> np.ndarray:
        """All regions -> the flat slot parameter vector (inactive slots are zeros).

        `now`: time (s) of the sample's x(0), for moving regions (None: each pose is taken as
        valid at x(0)); `predict` False freezes every region where it was at its stamp.

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
            values[i * ELLIPSE_SLOT_SIZE:(i + 1) * ELLIPSE_SLOT_SIZE] = e.slot_values(now, predict)
        base = self.max_ellipses * ELLIPSE_SLOT_SIZE
        width = polygon_slot_size(self.max_polygon_vertices)
        for i, poly in enumerate(polygons):
            values[base + i * width: base + (i + 1) * width] = poly.slot_values(self.max_polygon_vertices, now, predict)
        return values

    def chords(self, slots: ca.SX, a: tuple, b: tuple, elapsed_a: float, elapsed_b: float) -> ca.SX:
        """active * c^2 of every ellipse slot for the chord from a to b ((state point, output point or None)
        each; see ellipse_chord_sq), then 0 for every polygon slot [n_slots]."""
        terms = [ellipse_chord_sq(*a, *b, slots[i * ELLIPSE_SLOT_SIZE:(i + 1) * ELLIPSE_SLOT_SIZE], elapsed_a,
                                  elapsed_b) for i in range(self.max_ellipses)]
        return ca.vertcat(*terms, ca.SX.zeros(self.max_polygons))

    def depths(self, slots: ca.MX, state_point: ca.MX, output_point: ca.MX | None, elapsed: float = 0.0) -> ca.MX:
        """active * g of every slot at one point [n_slots], at the stage `elapsed` s after x(0).

        The penalty F is sum max(0, .)^2.
        """
        terms = [ellipse_depth(state_point, output_point, slots[i * ELLIPSE_SLOT_SIZE:(i + 1) * ELLIPSE_SLOT_SIZE],
                               elapsed)
                 for i in range(self.max_ellipses)]
        base = self.max_ellipses * ELLIPSE_SLOT_SIZE
        width = polygon_slot_size(self.max_polygon_vertices)
        for i in range(self.max_polygons):
            slot = slots[base + i * width: base + (i + 1) * width]
            terms.append(polygon_depth(state_point, output_point, slot, self.max_polygon_vertices, elapsed))
        return ca.vertcat(*terms)
