"""What the controller sees, as messages RViz and Foxglove draw: the predicted path, the regions in
use, the artificial steady state y_a, the target, and the numbers to plot.

Frames: a region or point lives in the `state` plane (the two state coordinates of `plane`) or the
`output` plane; `DisplayFrames` names the frame each is drawn in (for the paper's example the
abstract frames `state`/`output`, for a robot both are the odometry frame, e.g. `odom`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Point32, PolygonStamped, PoseStamped
from nav_msgs.msg import Path
from std_msgs.msg import ColorRGBA, Float64MultiArray, MultiArrayDimension
from visualization_msgs.msg import Marker, MarkerArray

from ..core.problem.regions import Region
from .markers import delete_all_marker, region_marker, yaw_to_quaternion

#: labels of the `~/stats` vector, in order (Foxglove plots `/controller/stats.data[i]`)
STATS_LABELS = ("solve_time_ms", "iterations", "offset_cost", "avoidance_cost", "tracking_cost")
_IN_USE = ColorRGBA(r=0.9, g=0.2, b=0.2, a=0.5)
_PREDICTED = ColorRGBA(r=0.9, g=0.5, b=0.1, a=0.15)
_STEADY = ColorRGBA(r=0.1, g=0.4, b=1.0, a=0.9)
_TARGET = ColorRGBA(r=0.1, g=0.8, b=0.2, a=0.9)


@dataclass(frozen=True)
class DisplayFrames:
    """frame_id of what lies in the state plane and in the output plane."""

    state: str = "state"
    output: str = "output"

    def of(self, plane_frame: str) -> str:
        return self.state if plane_frame == "state" else self.output


def prediction_path(states: np.ndarray, plane: Sequence[int], stamp: Time, frame: str,
                    heading_index: int | None = None) -> Path:
    """Predicted states x(0..N) [N+1, n] -> Path of their `plane` coordinates (yaw from `heading_index`)."""
    path = Path()
    path.header.stamp, path.header.frame_id = stamp, frame
    for x in states:
        pose = PoseStamped()
        pose.header = path.header
        pose.pose.position.x, pose.pose.position.y = float(x[plane[0]]), float(x[plane[1]])
        pose.pose.orientation = yaw_to_quaternion(0.0 if heading_index is None else float(x[heading_index]))
        path.poses.append(pose)
    return path


def regions_markers(regions: Sequence[Region], stamp: Time, frames: DisplayFrames,
                    predicted: Sequence[Sequence[Region]] = ()) -> MarkerArray:
    """The regions in use (ns `regions`), after a DELETEALL so the array is the complete set.

    `predicted`: for moving regions, the regions as the NLP sees them at each stage k = 1..N
    (ns `regions_predicted`, faint). Static regions pass nothing: stage k equals stage 0.
    """
    markers = [delete_all_marker()]
    for ns, stages, color in (("regions", [regions], _IN_USE), ("regions_predicted", predicted, _PREDICTED)):
        index = 0
        for stage in stages:
            for region in stage:
                marker = region_marker(region, index, ns, stamp)
                marker.header.frame_id = frames.of(region.frame)
                marker.color = color
                markers.append(marker)
                index += 1
    return MarkerArray(markers=markers)


def point_marker(point: Sequence[float], stamp: Time, frame: str, ns: str, color: ColorRGBA,
                 size: float = 0.15) -> Marker:
    """A SPHERE of diameter `size` at a plane point (x, y)."""
    marker = Marker(ns=ns, id=0, type=Marker.SPHERE, action=Marker.ADD, color=color)
    marker.header.stamp, marker.header.frame_id = stamp, frame
    marker.pose.position = Point(x=float(point[0]), y=float(point[1]), z=0.0)
    marker.pose.orientation.w = 1.0
    marker.scale.x = marker.scale.y = marker.scale.z = float(size)
    return marker


def steady_state_marker(x_a: Sequence[float], plane: Sequence[int], stamp: Time, frame: str) -> Marker:
    """y_a drawn where the plan ends: x_a's `plane` coordinates (for a robot, y_a itself)."""
    return point_marker((x_a[plane[0]], x_a[plane[1]]), stamp, frame, "steady_state", _STEADY)


def target_marker(point: Sequence[float], stamp: Time, frame: str) -> Marker:
    """The target y_t (its plane point) as a green sphere."""
    return point_marker(point, stamp, frame, "target", _TARGET)


def stats_array(solve_time: float, iterations: int, offset: float, avoidance: float,
                tracking: float) -> Float64MultiArray:
    """One sample's numbers to plot, labelled in the layout (STATS_LABELS; solve time in ms)."""
    values = [solve_time * 1e3, float(iterations), offset, avoidance, tracking]
    msg = Float64MultiArray(data=[float(v) if math.isfinite(v) else math.nan for v in values])
    msg.layout.dim = [MultiArrayDimension(label=",".join(STATS_LABELS), size=len(values), stride=len(values))]
    return msg


#: corners of the polygon drawn for a round body (footprint_radius)
ROUND_BODY_CORNERS = 24


def footprint_polygon(footprint: Sequence[float], radius: float, frame: str, stamp: Time) -> PolygonStamped:
    """The robot's body in `frame` (base_link): the footprint polygon (x1, y1, x2, y2, ... m) if given, else a
    circle of `radius` (m) as ROUND_BODY_CORNERS corners (nav2's footprint topic type)."""
    if len(footprint) >= 6:
        corners = list(zip(footprint[0::2], footprint[1::2], strict=True))
    else:
        angles = np.linspace(0.0, 2 * math.pi, ROUND_BODY_CORNERS, endpoint=False)
        corners = list(zip(radius * np.cos(angles), radius * np.sin(angles), strict=True))
    msg = PolygonStamped()
    msg.header.stamp, msg.header.frame_id = stamp, frame
    msg.polygon.points = [Point32(x=float(x), y=float(y), z=0.0) for x, y in corners]
    return msg
