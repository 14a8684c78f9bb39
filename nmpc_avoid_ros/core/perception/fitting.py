"""Points (m, odom) -> clusters -> the controller's region shapes: circles and thin boxes.

Clustering is single linkage cut at `cluster_gap`: two returns closer than the gap belong to one
object, and so do chains of them. `scipy.sparse.csgraph.connected_components` joins the close
pairs: exact single linkage without building the full dendrogram (scipy.cluster.hierarchy would,
O(K^2) in memory). The pairs of a scan are its neighbouring beams (O(K), a full turn closing on its
first beam), those of a grid's unordered cells every pair within the gap
(`scipy.spatial.cKDTree.query_pairs`, O(K log K)).

Each cluster is fitted by its principal axes (of its 2x2 covariance):

- thin (its returns within `wall_thickness` of a line) and at least `min_box_length` long: a wall
  segment, a rotated box whose near face runs through the returns and whose thickness extends
  away from the sensor (what lies behind a surface is not seen, and a wall has some);
- at most `max_circle_diameter` long: a circle. A laser sees only the near side of a round object,
  whose mean lies in front of its centre, so the centre is the algebraic least-squares circle fit
  (Kasa) of the returns; where they do not bend like an arc (a flat face: a box's side) the object is
  taken as deep as it is wide, its centre half its length behind the face. Either way the radius
  covers every return;
- otherwise (a corner, a room's walls seen as one chain): split where the chain of returns, in order
  of bearing from the sensor, bends most (Douglas-Peucker), and fit each piece, down to
  `max_split_depth` levels (then a box covering the piece).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import ConfigError
from ..problem.shapes import Ellipse, Polygon, rotated_box

CIRCLE, WALL = "circle", "wall"


@dataclass(frozen=True)
class FitSettings:
    """How returns become regions (lengths in m)."""

    #: returns closer than this belong to one object (and chains of them)
    cluster_gap: float = 0.25
    #: clusters with fewer returns are dropped as noise (1: every return counts, a thin pole too)
    min_points: int = 1
    #: a cluster at most this long is a circle (unless it is a thin, long enough wall segment)
    max_circle_diameter: float = 1.0
    #: a cluster whose returns lie within this of a line is a wall segment
    wall_thickness: float = 0.12
    #: a thin cluster shorter than this is a circle, not a wall segment
    min_box_length: float = 0.5
    #: the smallest circle radius (a single return)
    min_radius: float = 0.05
    #: returns bending less than this across their line (m) are a flat face, not an arc to fit a circle to
    min_arc_depth: float = 0.015
    #: the thickness of a box whose returns lie on a line
    min_box_thickness: float = 0.1
    #: splits of a cluster that is neither (a corner, a chain of walls)
    max_split_depth: int = 6
    #: clusters fitted at most, nearest first: bounds the work of a scan of noise (rain, dust, a broken sensor)
    max_clusters: int = 200
    #: a scan's neighbouring returns link up to r sin(dtheta) / sin(lambda - dtheta) apart, lambda this (rad;
    #: 0: the fixed gap only; Borges and Aldon's 10 degrees): see cluster_labels. In the shipped room world
    #: (360 beams) it cut the wall fragments fitted as one-return circles from 186 to 27 in 200 scans
    breakpoint_angle: float = math.radians(10.0)

    def __post_init__(self) -> None:
        for name in ("cluster_gap", "max_circle_diameter", "wall_thickness", "min_radius", "min_box_thickness",
                     "min_arc_depth"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive number of metres, got {value}")
        if not (math.isfinite(self.min_box_length) and self.min_box_length >= 0):
            raise ConfigError(f"min_box_length must be >= 0 m, got {self.min_box_length}")
        if not (math.isfinite(self.breakpoint_angle) and 0 <= self.breakpoint_angle < math.pi / 2):
            raise ConfigError(f"breakpoint_angle must be in [0, pi/2) rad, got {self.breakpoint_angle}")
        if self.min_points < 1 or self.max_split_depth < 0 or self.max_clusters < 1:
            raise ConfigError("min_points and max_clusters must be >= 1 and max_split_depth >= 0")


@dataclass(frozen=True)
class Fitted:
    """One fitted shape in odom: `kind` CIRCLE (`size` = (radius, radius)) or WALL (a box of `size` = (length,
    thickness) along `yaw`), its `center` (m), and its nearest return's distance (m) from the robot, by which the
    nearest are kept when there are more than the slots hold. The region itself is built on first use: only the
    kept ones pay for it."""

    kind: str
    center: tuple[float, float]
    size: tuple[float, float]
    yaw: float
    distance: float
    frame: str = "output"

    @cached_property
    def region(self) -> Ellipse | Polygon:
        if self.kind == CIRCLE:
            return Ellipse(self.center, self.size, 0.0, self.frame)
        return rotated_box(self.center, self.size, self.yaw, self.frame)

    @cached_property
    def planes(self) -> np.ndarray:
        """A wall's half-planes (nx, ny, b) [4, 3] (outward unit normals: inside iff n . p < b for all)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        normals = np.array([[c, s], [-s, c], [-c, -s], [s, -c]])
        half = np.array([self.size[0], self.size[1], self.size[0], self.size[1]]) / 2
        return np.column_stack([normals, normals @ np.asarray(self.center) + half])

    def inflated(self, margin: float) -> Fitted:
        """Grown by `margin` (m) on every side (a box's corners mitred: Polygon.inflated of a rectangle)."""
        grow = margin if self.kind == CIRCLE else 2 * margin
        return dataclasses.replace(self, size=(self.size[0] + grow, self.size[1] + grow))


def cluster_labels(points: np.ndarray, gap: float, ordered: bool = False, closed: bool = False,
                   sensor: np.ndarray | None = None, breakpoint_angle: float = 0.0) -> tuple[int, np.ndarray]:
    """Single-linkage clusters of points [K, 2] cut at `gap` (m): (count, label [K] in 0..count-1).

    `ordered`: the points are a scan's, in beam order, and only neighbouring beams (and, `closed`, the last and
    the first of a full turn) are linked, O(K) without a tree; otherwise every pair within the gap (a grid).
    An ordered scan with `breakpoint_angle` lambda > 0 (rad) seen from `sensor` [2] links two neighbouring
    returns up to r sin(dtheta) / sin(lambda - dtheta) apart where that is more than the gap (Borges and
    Aldon's adaptive breakpoint: r the nearer range, dtheta their angle apart): a surface seen at a grazing
    angle, its returns spread out, stays one object."""
    count = len(points)
    if count == 0:
        return 0, np.zeros(0, dtype=int)
    if ordered:
        first = np.arange(count if closed and count > 2 else count - 1)
        second = (first + 1) % count
        reach = np.full(len(first), gap)
        if breakpoint_angle > 0 and sensor is not None and len(first):
            rays = points - sensor
            ranges = np.hypot(*rays.T)
            bearing = np.arctan2(rays[:, 1], rays[:, 0])
            apart = np.abs((bearing[second] - bearing[first] + math.pi) % (2 * math.pi) - math.pi)
            grazing = apart < breakpoint_angle
            spread = np.minimum(ranges[first], ranges[second])[grazing] * np.sin(apart[grazing]) / np.sin(
                breakpoint_angle - apart[grazing])
            reach[grazing] = np.maximum(gap, spread)
        near = np.hypot(*(points[second] - points[first]).T) < reach
        pairs = np.column_stack([first[near], second[near]])
    else:
        pairs = cKDTree(points).query_pairs(gap, output_type="ndarray")
    graph = csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(count, count))
    # each pair once: weakly connected components of that graph are the undirected ones
    n, labels = connected_components(graph, directed=True, connection="weak")
    return int(n), labels


def fit_regions(points: np.ndarray, sensor: np.ndarray, robot: np.ndarray, settings: FitSettings,
                frame: str = "output", gap: float | None = None, ordered: bool = False, closed: bool = False,
                enough: tuple[int, int] | None = None, surface: bool = True) -> list[Fitted]:
    """Points [K, 2] (m) seen from `sensor` [2] -> fitted regions, nearest to `robot` [2] first.

    `gap` overrides settings.cluster_gap (a grid joins its neighbouring cells at its resolution); `ordered` and
    `closed` as in cluster_labels (a scan's points in beam order, a full turn). `enough` = (circles, walls): the
    clusters are fitted nearest first and the fitting stops once that many of each are nearer than every cluster
    left (the result's nearest ones are then exactly those of fitting all). At most settings.max_clusters clusters,
    the nearest, are fitted: a scan of noise, thousands of one-return clusters, costs what its nearest do.
    `surface`: the points are surfaces seen from the sensor (a scan); False: they fill the objects (a grid)."""
    n, labels = cluster_labels(points, settings.cluster_gap if gap is None else gap, ordered, closed, sensor,
                               settings.breakpoint_angle)
    if n == 0:
        return []
    # grouped by cluster, each in order of bearing from the sensor: one sort for all
    bearing = np.arctan2(points[:, 1] - sensor[1], points[:, 0] - sensor[0])
    order = np.lexsort((bearing, labels))
    bounds = np.searchsorted(labels[order], np.arange(n + 1))
    reach = np.hypot(*(points[order] - robot).T)
    nearest = np.minimum.reduceat(reach, bounds[:-1])  # every cluster has a point: no empty segment
    fitted: list[Fitted] = []
    for k in np.argsort(nearest, kind="stable")[: settings.max_clusters]:
        if enough is not None and _have_enough(fitted, enough, float(nearest[k])):
            break
        members = order[bounds[k]:bounds[k + 1]]
        if len(members) < settings.min_points:
            continue
        chain = points[_from_widest_gap(members, bearing[members])]
        for piece, axes in _pieces(chain, settings):
            distance = float(np.min(np.hypot(*(piece - robot).T)))
            fitted.append(_fit(piece, axes, sensor, settings, frame, distance, surface))
    fitted.sort(key=lambda f: f.distance)
    return fitted


def _have_enough(fitted: list[Fitted], enough: tuple[int, int], beyond: float) -> bool:
    """True when at least enough = (circles, walls) of `fitted` lie nearer than `beyond` (m)."""
    circles = sum(1 for f in fitted if f.kind == CIRCLE and f.distance <= beyond)
    return circles >= enough[0] and len([f for f in fitted if f.kind != CIRCLE and f.distance <= beyond]) >= enough[1]


def _from_widest_gap(members: np.ndarray, bearing: np.ndarray) -> np.ndarray:
    """A cluster's point indices in order of bearing (rad, sorted) from the sensor, started after the widest
    angular gap: a chain as the beams swept it, also where a cluster wraps past the scan's first beam (a
    grid's cells get the same order)."""
    if len(members) < 3:
        return members
    steps = np.empty(len(bearing))
    steps[:-1] = bearing[1:] - bearing[:-1]
    steps[-1] = bearing[0] + 2 * math.pi - bearing[-1]
    start = int(np.argmax(steps)) + 1
    return members if start == len(members) else np.concatenate([members[start:], members[:start]])


def _pieces(chain: np.ndarray, settings: FitSettings) -> list[tuple[np.ndarray, Axes]]:
    """A chain of points [K, 2] split where it bends (Douglas-Peucker: at the point farthest from the chord
    between its ends) until every piece is a wall segment or small enough for a circle: (piece, its axes)."""
    pieces, todo = [], [(chain, settings.max_split_depth)]
    while todo:
        points, depth = todo.pop()
        axes = _axes(points)
        length, width = axes.length, axes.width
        if depth == 0 or len(points) < 3 or length <= settings.max_circle_diameter or (
                width <= settings.wall_thickness and length >= settings.min_box_length):
            pieces.append((points, axes))
            continue
        chord = points[-1] - points[0]
        offsets = points - points[0]
        norm = float(np.hypot(*chord))
        # a closed chain (a ring around the sensor) has no chord: the farthest point from its start instead
        deviation = (np.abs(offsets[:, 0] * chord[1] - offsets[:, 1] * chord[0]) / norm if norm > 1e-6
                     else np.hypot(*offsets.T))
        split = int(np.clip(np.argmax(deviation), 1, len(points) - 2))
        # the bend's point goes with both halves: the corner is covered by both
        todo += [(points[: split + 1], depth - 1), (points[split:], depth - 1)]
    return pieces


@dataclass(frozen=True)
class Axes:
    """A piece's principal axes: `mean` [2] (m), unit `major` and `normal` [2], the points' coordinates
    `along` and `across` them [K] (m), and their spans `length` and `width` (m)."""

    mean: np.ndarray
    major: np.ndarray
    normal: np.ndarray
    along: np.ndarray
    across: np.ndarray
    length: float
    width: float


def _axes(points: np.ndarray) -> Axes:
    """The principal axes of points [K, 2]: the 2x2 covariance's eigenvectors in closed form (the axis angle
    0.5 atan2(2 sxy, sxx - syy)), a tenth of numpy.linalg.eigh's call cost."""
    mean = points.mean(axis=0)
    centred = points - mean
    x, y = centred.T
    angle = 0.5 * math.atan2(2.0 * float(x @ y), float(x @ x - y @ y))
    major = np.array([math.cos(angle), math.sin(angle)])
    normal = np.array([-major[1], major[0]])
    along, across = centred @ major, centred @ normal
    return Axes(mean, major, normal, along, across, float(along.max() - along.min()),
                float(across.max() - across.min()))


def _fit(points: np.ndarray, axes: Axes, sensor: np.ndarray, settings: FitSettings, frame: str,
         distance: float, surface: bool = True) -> Fitted:
    """One piece -> a wall segment's box, or a circle, or (a piece left too big) a covering box."""
    length, width = axes.length, axes.width
    if length <= settings.max_circle_diameter and not (
            width <= settings.wall_thickness and length >= settings.min_box_length):
        centre, radius = _circle(points, axes, sensor, settings, surface)
        return Fitted(CIRCLE, centre, (radius, radius), 0.0, distance, frame)
    middle, size, yaw = _box(axes, sensor, settings)
    return Fitted(WALL, middle, size, yaw, distance, frame)


def _box(axes: Axes, sensor: np.ndarray, settings: FitSettings) -> tuple[tuple[float, float], tuple[float, float],
                                                                         float]:
    """The thin box (centre (m), (length, thickness) (m), yaw (rad)) of a wall segment: its near face through the
    returns, its thickness away from `sensor`."""
    mean, major, normal, along, across = axes.mean, axes.major, axes.normal, axes.along, axes.across
    if float((mean - sensor) @ normal) < 0:  # make `normal` point away from the sensor
        normal, across = -normal, -across
    thickness = max(axes.width, settings.min_box_thickness)
    # half the smallest thickness past each end: the surface goes on to half a beam spacing past its last return
    length = axes.length + settings.min_box_thickness
    middle = mean + major * (along.max() + along.min()) / 2 + normal * (across.min() + thickness / 2)
    return (float(middle[0]), float(middle[1])), (length, thickness), math.atan2(major[1], major[0])


def _circle(points: np.ndarray, axes: Axes, sensor: np.ndarray, settings: FitSettings,
            surface: bool = True) -> tuple[tuple[float, float], float]:
    """The circle (centre (m), radius (m)) of a small cluster, its radius covering every return: the Kasa
    least-squares circle where the returns bend like an arc of one (the arc at least min_arc_depth deep, the
    radius at most max_circle_diameter / 2, the centre behind the returns); otherwise (a flat face, a box's
    side) an object taken as deep as it is wide: the centre half the length behind the face's middle (a
    square seen face-on: its circumscribed circle). Not `surface` (a grid's cells fill the object): the
    circle about their mean."""
    mean, length = axes.mean, axes.length
    if not surface:
        return (float(mean[0]), float(mean[1])), max(float(np.max(np.hypot(*(points - mean).T))), settings.min_radius)
    away = axes.normal if float((mean - sensor) @ axes.normal) >= 0 else -axes.normal
    centre = mean + away * (length / 2)
    if len(points) >= 3:
        local = points - mean  # centred: well-conditioned normal equations
        design = np.column_stack([2 * local, np.ones(len(local))])
        with np.errstate(all="ignore"):
            try:
                solution = np.linalg.solve(design.T @ design, design.T @ np.einsum("ij,ij->i", local, local))
            except np.linalg.LinAlgError:  # the returns on a line: no circle through them
                solution = np.full(3, np.nan)
        fitted = mean + solution[:2]
        radius_sq = solution[2] + solution[:2] @ solution[:2]
        if (np.all(np.isfinite(solution)) and 0 < radius_sq <= (settings.max_circle_diameter / 2) ** 2
                and axes.width >= settings.min_arc_depth and float((fitted - mean) @ (mean - sensor)) >= 0):
            centre = fitted
    radius = max(float(np.max(np.hypot(*(points - centre).T))), settings.min_radius)
    return (float(centre[0]), float(centre[1])), radius
