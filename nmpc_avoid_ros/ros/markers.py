"""Obstacle regions as visualization_msgs markers (docs/design.md, "Interfaces").

The `obstacles` topic carries a MarkerArray, so RViz and Foxglove draw exactly what the
controller avoids. `RegionStore` applies those messages with RViz's semantics:

- key (ns, id); ADD (== MODIFY == 0) adds or replaces, DELETE (2) removes, DELETEALL (3) clears
  every region regardless of ns (as in ROS 2); markers of one message apply in order;
- `lifetime` 0 = forever, otherwise the region expires `lifetime` seconds after it arrived
  (receipt time on the node clock, so skewed publisher clocks cannot expire it early);
- CYLINDER / SPHERE -> Ellipse (semi-axes scale.x/2, scale.y/2), CUBE -> rotated box,
  LINE_STRIP -> convex Polygon through `points` (transformed by `pose`, as RViz draws it);
- `header.frame_id` names the plane: 'state' or 'output' ('' -> the store's default).

Moving regions: `header.stamp` is the time the pose was valid. A velocity (plane units/s, in the
marker's plane) is either given explicitly as the token `velocity=<vx>,<vy>` in the marker's
`text` (RViz and Foxglove ignore `text` for these types, so the marker draws the same; other
tokens are left alone; a zero stamp then means "valid when received"), or estimated from
successive updates of the same (ns, id) with non-zero stamps (core/problem/motion.py: filtered, reset on
jumps, bounded by max_speed). A marker with a zero stamp and no explicit velocity is static.

A bad marker is rejected on its own, with a reason, and the previous region under its key stays
in force; nothing in a message can make the store raise.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from builtin_interfaces.msg import Duration, Time
from geometry_msgs.msg import Point, Quaternion
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from ..core.errors import InputError, RegionError
from ..core.problem.motion import VelocityEstimator
from ..core.problem.regions import FRAMES, Ellipse, Polygon, Region, SlotLayout, rotated_box
from .conversions import seconds_to_duration, seconds_to_time, stamp_to_seconds

ADD = 0  # Marker.ADD == Marker.MODIFY == 0 in ROS 2
DELETE = 2
DELETEALL = 3
CUBE, SPHERE, CYLINDER, LINE_STRIP = 1, 2, 3, 4
_ELLIPSE_TYPES = (SPHERE, CYLINDER)
_TYPE_NAMES = {
    0: "ARROW", 1: "CUBE", 2: "SPHERE", 3: "CYLINDER", 4: "LINE_STRIP", 5: "LINE_LIST", 6: "CUBE_LIST",
    7: "SPHERE_LIST", 8: "POINTS", 9: "TEXT_VIEW_FACING", 10: "MESH_RESOURCE", 11: "TRIANGLE_LIST",
    12: "ARROW_STRIP",
}
QUATERNION_TOLERANCE = 1e-3
#: id reported for a rejection that concerns the whole message rather than one marker
MESSAGE_ID = -1


@dataclass
class ApplyReport:
    """Outcome of one `RegionStore.apply`.

    applied: ADD markers that added or replaced a region; deleted: regions removed by DELETE or
    DELETEALL; rejected: (ns, id, reason) per refused marker (id MESSAGE_ID = the whole message);
    changed: the stored regions differ from before the message (a moving one that moved counts);
    keys_changed: which regions are stored (their ns/id) differs (what a log line reports: a feed of
    moving obstacles changes the regions every message, the set rarely); resets: (ns, id, reason)
    per accepted marker whose velocity estimate was reset (a jump, a skewed or decreasing stamp);
    malformed: (ns, id) of the rejected markers that were not Marker-like objects (an attribute missing or
    of the wrong type: the catch-all, which a real Marker never reaches).
    """

    applied: int = 0
    deleted: int = 0
    rejected: list[tuple[str, int, str]] = field(default_factory=list)
    changed: bool = False
    keys_changed: bool = False
    resets: list[tuple[str, int, str]] = field(default_factory=list)
    malformed: list[tuple[str, int]] = field(default_factory=list)


@dataclass(frozen=True)
class _Entry:
    region: Region
    expires_at: float  # node-clock seconds; math.inf = never


class RegionStore:
    """Obstacle regions keyed by (ns, id), fed by MarkerArray messages.

    Capacities mirror the NLP's fixed parameter slots (`SlotLayout`), so whatever the store holds
    can always be packed: an ADD that would exceed them is rejected instead of failing later.
    """

    def __init__(
        self,
        max_ellipses: int = 8,
        max_polygons: int = 4,
        max_polygon_vertices: int = 8,
        default_frame: str = "state",
        output_frame_available: bool = True,
        max_markers_per_message: int = 1000,
        max_speed: float = 3.0,
        max_stamp_skew: float = 2.0,
        frame_aliases: Mapping[str, str] | None = None,
    ) -> None:
        if default_frame not in FRAMES:
            raise InputError(f"default_frame must be one of {FRAMES}, got {default_frame!r}")
        if min(max_ellipses, max_polygons) < 0 or max_polygon_vertices < 3 or max_markers_per_message < 1:
            raise InputError("capacities must be >= 0, max_polygon_vertices >= 3, max_markers_per_message >= 1")
        if not output_frame_available and default_frame == "output":
            raise InputError("default_frame 'output' needs an output with at least 2 coordinates")
        self.max_ellipses = int(max_ellipses)
        self.max_polygons = int(max_polygons)
        self.max_polygon_vertices = int(max_polygon_vertices)
        self.default_frame = default_frame
        self.output_frame_available = bool(output_frame_available)
        self.max_markers_per_message = int(max_markers_per_message)
        # e.g. {"odom": "output"}: a robot stack's markers in its odometry frame are positions
        self.frame_aliases = dict(frame_aliases or {})
        if any(plane not in FRAMES for plane in self.frame_aliases.values()):
            raise InputError(f"frame_aliases must map to one of {FRAMES}, got {self.frame_aliases}")
        self._entries: dict[tuple[str, int], _Entry] = {}
        self._revision = 0
        self.motion = VelocityEstimator(max_speed, max_stamp_skew)

    @classmethod
    def from_layout(cls, layout: SlotLayout, **kwargs: object) -> RegionStore:
        """A store whose capacities are those of an NLP slot layout."""
        return cls(layout.max_ellipses, layout.max_polygons, layout.max_polygon_vertices, **kwargs)  # type: ignore[arg-type]

    @property
    def revision(self) -> int:
        """Counter bumped whenever the stored regions change (message or expiry): repack when it moves."""
        return self._revision

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        """Forget every region (e.g. on a controller reset)."""
        self.motion.forget()
        if self._entries:
            self._entries.clear()
            self._revision += 1

    def active(self, now: float) -> tuple[Region, ...]:
        """Regions alive at `now` (node-clock seconds), sorted by (ns, id); expired ones are dropped."""
        self._expire(_check_now(now))
        return tuple(self._entries[key].region for key in sorted(self._entries))

    def active_items(self, now: float) -> tuple[tuple[tuple[str, int], Region], ...]:
        """Like `active` but with the (ns, id) key of each region, for diagnostics."""
        self._expire(_check_now(now))
        return tuple((key, self._entries[key].region) for key in sorted(self._entries))

    def apply(self, msg: MarkerArray, now: float) -> ApplyReport:
        """Apply one MarkerArray received at `now` (node-clock seconds); never raises on its content."""
        now = _check_now(now)
        report = ApplyReport()
        markers = getattr(msg, "markers", None)
        try:
            count = len(markers)  # type: ignore[arg-type]
        except TypeError:
            report.rejected.append(("", MESSAGE_ID, "message has no marker list"))
            return report
        if count > self.max_markers_per_message:
            # checked before touching any marker, so a flood costs O(1) and leaves the store as it was
            report.rejected.append(
                ("", MESSAGE_ID, f"message has {count} markers, more than the limit {self.max_markers_per_message}; "
                                 "ignored as a whole"))
            return report
        self._expire(now)
        before = {key: entry.region for key, entry in self._entries.items()}
        for marker in markers:
            ns, marker_id = _key_of(marker)
            try:
                self._apply_one(marker, (ns, marker_id), now, report)
            except (RegionError, InputError) as exc:
                report.rejected.append((ns, marker_id, str(exc) or type(exc).__name__))
            except Exception as exc:  # a malformed message object must never crash the node
                report.rejected.append((ns, marker_id, f"malformed marker: {type(exc).__name__}: {exc}"))
                report.malformed.append((ns, marker_id))
        after = {key: entry.region for key, entry in self._entries.items()}
        # velocity tracks live as long as their regions; checked after the whole message, so a
        # DELETEALL followed by the same keys (a publisher replacing its set) keeps the estimates
        self.motion.retain(after)
        report.changed, report.keys_changed = after != before, after.keys() != before.keys()
        if report.changed:
            self._revision += 1
        return report

    # --- internals -------------------------------------------------------------------------------

    def _expire(self, now: float) -> None:
        dead = [key for key, entry in self._entries.items() if entry.expires_at <= now]
        for key in dead:
            del self._entries[key]
            self.motion.forget(key)
        if dead:
            self._revision += 1

    def _apply_one(self, marker: Marker, key: tuple[str, int], now: float, report: ApplyReport) -> None:
        action = int(marker.action)
        if action == DELETEALL:
            report.deleted += len(self._entries)
            self._entries.clear()
            return
        if action == DELETE:
            if self._entries.pop(key, None) is not None:
                report.deleted += 1
            return
        if action != ADD:
            raise InputError(f"unknown action {action} (use ADD/MODIFY=0, DELETE=2, DELETEALL=3)")
        lifetime = stamp_to_seconds(marker.lifetime)
        if not math.isfinite(lifetime) or lifetime < 0:
            raise InputError(f"lifetime must be >= 0 s (0 = forever), got {lifetime}")
        region = self.marker_to_region(marker)
        self._check_capacity(region, key)
        stamp, explicit = stamp_to_seconds(marker.header.stamp), velocity_from_text(marker.text)
        if stamp == 0 and explicit is None:
            # no stamp to estimate from (a hand-published marker): static, as it always was
            self.motion.forget(key)
        else:
            stamp = stamp or now  # an explicit velocity without a stamp: the pose is valid when received
            estimate = self.motion.update(key, region.reference_point, stamp, now, explicit)
            if estimate.reset:
                report.resets.append((*key, estimate.reset))
            if estimate.velocity != (0.0, 0.0):
                region = region.with_motion(estimate.velocity, stamp)
        self._entries[key] = _Entry(region, now + lifetime if lifetime > 0 else math.inf)
        report.applied += 1

    def _check_capacity(self, region: Region, key: tuple[str, int]) -> None:
        kind = type(region)
        # a replacement of the same kind frees its own slot first
        used = sum(1 for k, e in self._entries.items() if k != key and type(e.region) is kind)
        capacity = self.max_ellipses if kind is Ellipse else self.max_polygons
        if used >= capacity:
            name = "ellipses (CYLINDER/SPHERE)" if kind is Ellipse else "polygons (CUBE/LINE_STRIP)"
            raise RegionError(f"capacity of {capacity} {name} reached; delete one first")

    def marker_to_region(self, marker: Marker) -> Region:
        """One ADD marker -> a core region; raises RegionError/InputError with a reason if invalid."""
        marker_type = int(marker.type)
        frame = self._frame_of(marker)
        yaw = quaternion_to_yaw(marker.pose.orientation)
        cx, cy = _finite_pair("pose.position", marker.pose.position.x, marker.pose.position.y)
        if marker_type in _ELLIPSE_TYPES or marker_type == CUBE:
            sx, sy = _finite_pair("scale", marker.scale.x, marker.scale.y)
            if sx <= 0 or sy <= 0:
                raise RegionError(f"scale.x and scale.y must be positive, got ({sx}, {sy})")
            if marker_type == CUBE:
                return rotated_box((cx, cy), (sx, sy), yaw, frame)
            return Ellipse((cx, cy), (sx / 2, sy / 2), yaw, frame)
        if marker_type == LINE_STRIP:
            points = marker.points
            # a closed strip repeats its first point, hence the + 1; checked before any per-point work
            if len(points) > self.max_polygon_vertices + 1:
                raise RegionError(f"LINE_STRIP has {len(points)} points, more than the capacity of "
                                  f"{self.max_polygon_vertices} vertices")
            if len(points) < 3:
                raise RegionError(f"LINE_STRIP needs at least 3 points, got {len(points)}")
            c, s = math.cos(yaw), math.sin(yaw)
            vertices = []
            for p in points:
                px, py = _finite_pair("point", p.x, p.y)
                # RViz draws points in the marker's pose frame: apply it so both agree
                vertices.append((cx + c * px - s * py, cy + s * px + c * py))
            polygon = Polygon(tuple(vertices), frame)
            if len(polygon.vertices) > self.max_polygon_vertices:
                raise RegionError(f"polygon has {len(polygon.vertices)} vertices, more than the capacity of "
                                  f"{self.max_polygon_vertices}")
            return polygon
        name = _TYPE_NAMES.get(marker_type, "unknown")
        raise RegionError(f"unsupported marker type {marker_type} ({name}); use CYLINDER, SPHERE, CUBE or LINE_STRIP")

    def _frame_of(self, marker: Marker) -> str:
        frame = marker.header.frame_id or self.default_frame
        frame = self.frame_aliases.get(frame, frame)
        if frame not in FRAMES:
            known = ", ".join(repr(f) for f in (*FRAMES, *self.frame_aliases))
            raise RegionError(f"header.frame_id must be {known} or empty, got {frame!r}")
        if frame == "output" and not self.output_frame_available:
            raise RegionError("frame 'output' is not available: this model's output has fewer than 2 coordinates")
        return frame


def _check_now(now: float) -> float:
    now = float(now)
    if not math.isfinite(now):
        raise InputError(f"now must be finite seconds, got {now}")
    return now


def _key_of(marker: object) -> tuple[str, int]:
    """(ns, id) of a marker, tolerant of garbage so a rejection can always be reported."""
    try:
        ns = str(marker.ns)  # type: ignore[attr-defined]
    except Exception:  # garbage marker object: still report it
        ns = ""
    try:
        marker_id = int(marker.id)  # type: ignore[attr-defined]
    except Exception:  # garbage marker object: still report it
        marker_id = MESSAGE_ID
    return ns, marker_id


def _finite_pair(name: str, x: float, y: float) -> tuple[float, float]:
    x, y = float(x), float(y)
    if not (math.isfinite(x) and math.isfinite(y)):
        raise RegionError(f"{name} contains NaN or infinite values: ({x}, {y})")
    return x, y


#: the token of a marker's `text` that carries an explicit velocity: velocity=<vx>,<vy>
VELOCITY_KEY = "velocity="


def velocity_from_text(text: str) -> tuple[float, float] | None:
    """The explicit velocity in a marker's `text` (None without a `velocity=` token).

    Tokens are separated by whitespace or ';'. InputError for a token that is not two finite
    numbers separated by a comma.
    """
    for token in str(text).replace(";", " ").split():
        if token.startswith(VELOCITY_KEY):
            parts = token[len(VELOCITY_KEY):].split(",")
            try:
                vx, vy = (float(v) for v in parts)
            except ValueError:
                raise InputError(f"text token {token!r}: velocity must be two numbers 'velocity=vx,vy'") from None
            if not (math.isfinite(vx) and math.isfinite(vy)):
                raise InputError(f"text token {token!r}: velocity contains NaN or infinite values")
            return vx, vy
    return None


def velocity_text(velocity: Sequence[float]) -> str:
    """The `text` token of an explicit velocity (exact float reprs)."""
    return f"{VELOCITY_KEY}{float(velocity[0])!r},{float(velocity[1])!r}"


def quaternion_to_yaw(q: Quaternion, tolerance: float = QUATERNION_TOLERANCE) -> float:
    """Yaw (rad, in [-pi, pi]) of a rotation about z.

    The all-zero quaternion (what a hand-written `ros2 topic pub` message or a JSON bridge may
    leave) is read as identity. Raises RegionError for a non-finite or non-unit quaternion, or a
    rotation that tilts the plane (a tilted region would not be what RViz draws in the plane).
    """
    x, y, z, w = (float(q.x), float(q.y), float(q.z), float(q.w))
    if not all(math.isfinite(v) for v in (x, y, z, w)):
        raise RegionError("pose.orientation contains NaN or infinite values")
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if norm == 0.0:
        return 0.0
    if abs(norm - 1.0) > tolerance:
        raise RegionError(f"pose.orientation must be a unit quaternion, norm is {norm:.6g}")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    if math.hypot(x, y) > tolerance:
        raise RegionError("pose.orientation must be a rotation about z only (roll/pitch not allowed)")
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_to_quaternion(yaw: float) -> Quaternion:
    """Rotation by `yaw` rad about z."""
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


# --- building markers (publishing, visualisation, tests, demos) ------------------------------------

_DEFAULT_FILL = (0.9, 0.2, 0.2, 0.5)
_DEFAULT_LINE = (0.9, 0.2, 0.2, 1.0)
LINE_WIDTH = 0.02  # scale.x of a LINE_STRIP is its drawn width (plane units); 0 would be invisible


def _stamp(stamp: Time | float | None) -> Time:
    if stamp is None:
        return Time()
    if isinstance(stamp, Time):
        return stamp
    return seconds_to_time(float(stamp))


def _color(rgba: Sequence[float]) -> ColorRGBA:
    r, g, b, a = (float(v) for v in rgba)
    return ColorRGBA(r=r, g=g, b=b, a=a)


def _base_marker(frame: str, marker_id: int, ns: str, stamp: Time | float | None, lifetime: float) -> Marker:
    marker = Marker()
    marker.header.frame_id = frame
    marker.header.stamp = _stamp(stamp)
    marker.ns = ns
    marker.id = int(marker_id)
    marker.action = ADD
    marker.lifetime = seconds_to_duration(lifetime) if lifetime > 0 else Duration()
    return marker


def ellipse_marker(
    ellipse: Ellipse,
    marker_id: int = 0,
    ns: str = "nmpc_regions",
    stamp: Time | float | None = None,
    lifetime: float = 0.0,
    color: Sequence[float] = _DEFAULT_FILL,
    height: float = 0.01,
) -> Marker:
    """Ellipse -> CYLINDER marker (scale = full axes 2a x 2b x `height`), frame = ellipse.frame.

    `lifetime` in seconds, 0 = forever; `stamp` a Time or seconds (None = zero stamp).
    """
    marker = _base_marker(ellipse.frame, marker_id, ns, stamp, lifetime)
    marker.type = CYLINDER
    marker.pose.position = Point(x=ellipse.center[0], y=ellipse.center[1], z=0.0)
    marker.pose.orientation = yaw_to_quaternion(ellipse.yaw)
    marker.scale.x = 2.0 * ellipse.semi_axes[0]
    marker.scale.y = 2.0 * ellipse.semi_axes[1]
    marker.scale.z = float(height)
    marker.color = _color(color)
    return marker


def polygon_marker(
    polygon: Polygon,
    marker_id: int = 0,
    ns: str = "nmpc_regions",
    stamp: Time | float | None = None,
    lifetime: float = 0.0,
    color: Sequence[float] = _DEFAULT_LINE,
    line_width: float = LINE_WIDTH,
) -> Marker:
    """Polygon -> closed LINE_STRIP marker (first vertex repeated), identity pose."""
    marker = _base_marker(polygon.frame, marker_id, ns, stamp, lifetime)
    marker.type = LINE_STRIP
    marker.pose.orientation = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    marker.scale.x = float(line_width)
    marker.points = [Point(x=vx, y=vy, z=0.0) for vx, vy in (*polygon.vertices, polygon.vertices[0])]
    marker.color = _color(color)
    return marker


def region_marker(region: Region, marker_id: int = 0, ns: str = "nmpc_regions",
                  stamp: Time | float | None = None, lifetime: float = 0.0) -> Marker:
    """Any core region -> its marker (ellipse -> CYLINDER, polygon -> LINE_STRIP).

    A moving region is drawn where it is at `stamp` (its own stamp if None) and carries its
    velocity in `text` (`velocity=vx,vy`).
    """
    if not isinstance(region, (Ellipse, Polygon)):
        raise RegionError(f"not a region: {region!r}")
    if region.moving:
        if stamp is None:
            stamp = region.stamp
        region = region.at(stamp_to_seconds(stamp) if isinstance(stamp, Time) else float(stamp))
    if isinstance(region, Ellipse):
        marker = ellipse_marker(region, marker_id, ns, stamp, lifetime)
    else:
        marker = polygon_marker(region, marker_id, ns, stamp, lifetime)
    if region.moving:
        marker.text = velocity_text(region.velocity)
    return marker


def delete_marker(ns: str, marker_id: int) -> Marker:
    """DELETE of the region (ns, id)."""
    marker = Marker()
    marker.ns = ns
    marker.id = int(marker_id)
    marker.action = DELETE
    return marker


def delete_all_marker() -> Marker:
    """DELETEALL: clears every region of the receiving store, whatever its ns."""
    marker = Marker()
    marker.action = DELETEALL
    return marker


def regions_to_markers(
    regions: Sequence[Region],
    stamp: Time | float | None = None,
    ns: str = "nmpc_regions",
    lifetime: float = 0.0,
    replace: bool = True,
) -> MarkerArray:
    """Regions -> MarkerArray with ids 0..n-1 in `ns`, each in its region's frame.

    With `replace` the array starts with DELETEALL, so on a latched (transient local) topic it
    stands for the complete set and regions dropped since the last message disappear.
    """
    markers = [delete_all_marker()] if replace else []
    markers.extend(region_marker(r, i, ns, stamp, lifetime) for i, r in enumerate(regions))
    return MarkerArray(markers=markers)
