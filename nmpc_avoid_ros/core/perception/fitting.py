"""Points (m, odom) -> clusters -> the controller's region shapes: circles and thin boxes.

Clustering is single linkage cut at `cluster_gap`: two returns closer than the gap belong to one
object, and so do chains of them. `scipy.spatial.cKDTree.query_pairs` finds the close pairs
(O(K log K)) and `scipy.sparse.csgraph.connected_components` joins them: exact single linkage
without building the full dendrogram (scipy.cluster.hierarchy would, O(K^2) in memory), the same
for an ordered scan (a full turn wraps around) and for the unordered cells of a grid.

Each cluster is fitted by its principal axes (of its 2x2 covariance):

- thin (its returns within `wall_thickness` of a line) and at least `min_box_length` long: a wall
  segment, a rotated box whose near face runs through the returns and whose thickness extends
  away from the sensor (what lies behind a surface is not seen, and a wall has some);
- at most `max_circle_diameter` long: a circle. A laser sees only the near side of a round object,
  whose mean lies in front of its centre, so the centre is the algebraic least-squares circle fit
  (Kasa) of the returns; where that fit is implausible (a flat or noisy arc) the circle around the
  cluster's mean. Either way the radius covers every return;
- otherwise (a corner, a room's walls seen as one chain): split where the chain of returns, in order
  of bearing from the sensor, bends most (Douglas-Peucker), and fit each piece, down to
  `max_split_depth` levels (then a box covering the piece).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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
    #: the thickness of a box whose returns lie on a line
    min_box_thickness: float = 0.1
    #: splits of a cluster that is neither (a corner, a chain of walls)
    max_split_depth: int = 6

    def __post_init__(self) -> None:
        for name in ("cluster_gap", "max_circle_diameter", "wall_thickness", "min_radius", "min_box_thickness"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive number of metres, got {value}")
        if not (math.isfinite(self.min_box_length) and self.min_box_length >= 0):
            raise ConfigError(f"min_box_length must be >= 0 m, got {self.min_box_length}")
        if self.min_points < 1 or self.max_split_depth < 0:
            raise ConfigError("min_points must be >= 1 and max_split_depth >= 0")


@dataclass(frozen=True)
class Fitted:
    """One fitted region: `kind` (CIRCLE or WALL), the region (odom), and its nearest return's distance (m)
    from the robot, by which the nearest regions are kept when there are more than the slots hold."""

    kind: str
    region: Ellipse | Polygon
    distance: float


def cluster_labels(points: np.ndarray, gap: float) -> tuple[int, np.ndarray]:
    """Single-linkage clusters of points [K, 2] cut at `gap` (m): (count, label [K] in 0..count-1)."""
    count = len(points)
    if count == 0:
        return 0, np.zeros(0, dtype=int)
    pairs = cKDTree(points).query_pairs(gap, output_type="ndarray")
    graph = csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(count, count))
    # each pair once (i < j): weakly connected components of that graph are the undirected ones
    n, labels = connected_components(graph, directed=True, connection="weak")
    return int(n), labels


def fit_regions(points: np.ndarray, sensor: np.ndarray, robot: np.ndarray, settings: FitSettings,
                frame: str = "output", gap: float | None = None) -> list[Fitted]:
    """Points [K, 2] (m) seen from `sensor` [2] -> fitted regions, nearest to `robot` [2] first.

    `gap` overrides settings.cluster_gap (a grid joins its neighbouring cells at its resolution)."""
    n, labels = cluster_labels(points, settings.cluster_gap if gap is None else gap)
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(n + 1))
    fitted: list[Fitted] = []
    for k in range(n):
        cluster = points[order[bounds[k]:bounds[k + 1]]]
        if len(cluster) < settings.min_points:
            continue
        for piece, axes in _pieces(cluster[_chain_order(cluster, sensor)], settings):
            kind, region = _fit(piece, axes, sensor, settings, frame)
            fitted.append(Fitted(kind, region, float(np.min(np.hypot(*(piece - robot).T)))))
    fitted.sort(key=lambda f: f.distance)
    return fitted


def _chain_order(points: np.ndarray, sensor: np.ndarray) -> np.ndarray:
    """Indices that put a cluster's points [K, 2] in order of bearing from the sensor [2], starting after the
    widest angular gap: a scan's beam order, also where a cluster wraps past the scan's first beam, and an
    order for a grid's cells."""
    bearing = np.arctan2(points[:, 1] - sensor[1], points[:, 0] - sensor[0])
    order = np.argsort(bearing, kind="stable")
    if len(order) < 3:
        return order
    steps = np.diff(bearing[order], append=bearing[order[0]] + 2 * math.pi)
    return np.roll(order, -(int(np.argmax(steps)) + 1))


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
    `along` and `across` them [K] (m)."""

    mean: np.ndarray
    major: np.ndarray
    normal: np.ndarray
    along: np.ndarray
    across: np.ndarray

    @property
    def length(self) -> float:
        return float(np.ptp(self.along))

    @property
    def width(self) -> float:
        return float(np.ptp(self.across))


def _axes(points: np.ndarray) -> Axes:
    """The principal axes of points [K, 2]: the 2x2 covariance's eigenvectors in closed form (the axis angle
    0.5 atan2(2 sxy, sxx - syy)), a tenth of numpy.linalg.eigh's call cost."""
    mean = points.mean(axis=0)
    centred = points - mean
    x, y = centred.T
    angle = 0.5 * math.atan2(2.0 * float(x @ y), float(x @ x - y @ y))
    major = np.array([math.cos(angle), math.sin(angle)])
    normal = np.array([-major[1], major[0]])
    return Axes(mean, major, normal, centred @ major, centred @ normal)


def _fit(points: np.ndarray, axes: Axes, sensor: np.ndarray, settings: FitSettings,
         frame: str) -> tuple[str, Ellipse | Polygon]:
    """One piece -> (kind, region): a wall segment's box, or a circle, or (a piece left too big) a covering box."""
    length, width = axes.length, axes.width
    if length <= settings.max_circle_diameter and not (
            width <= settings.wall_thickness and length >= settings.min_box_length):
        return CIRCLE, _circle(points, axes.mean, sensor, settings, frame)
    return WALL, _box(axes, sensor, settings, frame)


def _box(axes: Axes, sensor: np.ndarray, settings: FitSettings, frame: str) -> Polygon:
    """The thin box of a wall segment: its near face through the returns, its thickness away from `sensor`."""
    mean, major, normal, along, across = axes.mean, axes.major, axes.normal, axes.along, axes.across
    if float((mean - sensor) @ normal) < 0:  # make `normal` point away from the sensor
        normal, across = -normal, -across
    thickness = max(float(np.ptp(across)), settings.min_box_thickness)
    # half the smallest thickness past each end: the surface goes on to half a beam spacing past its last return
    length = float(np.ptp(along)) + settings.min_box_thickness
    middle = mean + major * (along.max() + along.min()) / 2 + normal * (across.min() + thickness / 2)
    return rotated_box(middle, (length, thickness), math.atan2(major[1], major[0]), frame)


def _circle(points: np.ndarray, mean: np.ndarray, sensor: np.ndarray, settings: FitSettings, frame: str) -> Ellipse:
    """The circle of a small cluster: the Kasa least-squares fit where plausible, its radius covering every return."""
    centre = mean
    if len(points) >= 3:
        local = points - mean  # centred: a well-conditioned least-squares problem
        design = np.column_stack([2 * local, np.ones(len(local))])
        solution, *_ = np.linalg.lstsq(design, np.einsum("ij,ij->i", local, local), rcond=None)
        fitted = mean + solution[:2]
        radius_sq = solution[2] + solution[:2] @ solution[:2]
        # plausible: a real radius no larger than the cluster may be, the centre behind the returns
        if (np.all(np.isfinite(solution)) and 0 < radius_sq <= settings.max_circle_diameter ** 2
                and float((fitted - mean) @ (mean - sensor)) >= 0):
            centre = fitted
    radius = max(float(np.max(np.hypot(*(points - centre).T))), settings.min_radius)
    return Ellipse((float(centre[0]), float(centre[1])), (radius, radius), 0.0, frame)
