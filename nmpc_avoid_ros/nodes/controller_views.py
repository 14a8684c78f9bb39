"""The controller's outputs for people and tools (config/*.rviz, config/*.foxglove.json):
`~/prediction` (Path), `~/regions` (MarkerArray), `~/steady_state` and `~/target_marker` (Marker),
`~/stats` (Float64MultiArray) and `~/certificate` (Float64MultiArray), the latched `~/goal_reached` (std_msgs/Bool,
transient local; nodes/controller_goal.py), for a robot with a body (`footprint_radius`, `footprint`) the latched
`~/footprint` (geometry_msgs/PolygonStamped in its base frame, as nav2 publishes it); the /diagnostics message."""

from __future__ import annotations

import json

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PolygonStamped
from nav_msgs.msg import Path
from rclpy.node import Node
from std_msgs.msg import Bool, Float64MultiArray, MultiArrayDimension
from visualization_msgs.msg import Marker, MarkerArray

from ..core.config.settings import ControllerSettings
from ..core.errors import RegionError
from ..core.loop.certificate import LAYOUT, CertificateSample
from ..core.sample.step_result import StepResult
from ..ros.parameters import LATCHED_QOS, STREAM_QOS
from ..ros.visualization import (
    footprint_polygon,
    prediction_path,
    regions_markers,
    stats_array,
    steady_state_marker,
    target_marker,
)
from .controller_io import ArrayInterface, RobotInterface


class ControllerViews:
    """Publishers of what one sample used and planned; created at configure, destroyed at cleanup."""

    def __init__(self, node: Node, io: ArrayInterface | RobotInterface) -> None:
        self.node, self.io = node, io
        self.prediction = node.create_publisher(Path, "~/prediction", STREAM_QOS)
        self.regions = node.create_publisher(MarkerArray, "~/regions", STREAM_QOS)
        self.steady_state = node.create_publisher(Marker, "~/steady_state", STREAM_QOS)
        self.target = node.create_publisher(Marker, "~/target_marker", STREAM_QOS)
        self.stats = node.create_publisher(Float64MultiArray, "~/stats", STREAM_QOS)
        self.certificate = node.create_publisher(Float64MultiArray, "~/certificate", STREAM_QOS)
        self.certificate_layout = [MultiArrayDimension(label=",".join(LAYOUT), size=len(LAYOUT), stride=len(LAYOUT))]
        self.goal_reached = node.create_publisher(Bool, "~/goal_reached", LATCHED_QOS)
        self.publish_goal_reached(False)  # a late joiner hears where things stand
        self.footprint = node.create_publisher(PolygonStamped, "~/footprint", LATCHED_QOS)
        self._body: tuple | None = None  # the body last published (footprint, radius)
        self.publish_footprint(node.controller.settings)

    def publish_footprint(self, settings: ControllerSettings) -> None:
        """The body, once and whenever it changes (a robot interface with a body only: its base frame)."""
        body = (tuple(settings.footprint), settings.footprint_radius)
        base = getattr(self.io, "base_frame", None)
        if base is None or settings.body_radius <= 0 or body == self._body:
            return
        self._body = body
        self.footprint.publish(footprint_polygon(*body, base, self.node.get_clock().now().to_msg()))

    def publish(self, result: StepResult, settings: ControllerSettings, regions: tuple, state_time: float,
                target: np.ndarray | None) -> None:
        """The plan of `result`, the regions at `state_time` (s, node clock) and, for moving ones, at
        each later stage of the horizon as the NLP predicts them."""
        stamp = self.node.get_clock().now().to_msg()
        self.publish_footprint(settings)
        plane, frames = settings.plane, self.io.frames
        self.prediction.publish(prediction_path(result.states, plane, stamp, frames.state, self.io.heading_index))
        try:
            now = [region.at(state_time) for region in regions]
            predicted = []
            if settings.predict_obstacles:
                predicted = [[region.at(state_time + k * settings.sample_time) for region in regions if region.moving]
                             for k in range(1, result.states.shape[0])]  # the plan's stages (passage mode: more)
            self.regions.publish(regions_markers(now, stamp, frames, predicted))
        except RegionError as exc:  # a region that cannot be moved in time (node.region_issue): the rest goes on
            self.node.region_issue("~/regions not published", exc)
        if np.all(np.isfinite(result.x_a)):
            self.steady_state.publish(steady_state_marker(result.x_a, plane, stamp, frames.state))
        if target is not None and target.size >= 2:
            self.target.publish(target_marker(target[list(settings.output_plane)], stamp, frames.output))
        self.stats.publish(stats_array(result.solve_time, result.iterations, result.offset_cost,
                                       result.avoidance_cost, result.tracking_cost))

    def publish_certificate(self, sample: CertificateSample) -> None:
        msg = Float64MultiArray(data=sample.as_vector())
        msg.layout.dim = self.certificate_layout
        self.certificate.publish(msg)

    def publish_goal_reached(self, reached: bool) -> None:
        self.goal_reached.publish(Bool(data=bool(reached)))

    def destroy(self) -> None:
        for publisher in (self.prediction, self.regions, self.steady_state, self.target, self.stats, self.certificate,
                          self.goal_reached, self.footprint):
            self.node.destroy_publisher(publisher)


def diagnostic_array(name: str, stamp: Time, level: bytes, message: str, values: dict[str, str],
                     result: StepResult | None, latency: float, state_time: float | None,
                     cert: CertificateSample | None) -> DiagnosticArray:
    """The controller's /diagnostics message: the node's `values`, then the sample's and the certificate's."""
    values = dict(values)
    if result is not None:
        values.update({
            "status": result.status, "solver_status": result.solver_status,
            "iterations": str(result.iterations), "solve_time_ms": f"{result.solve_time * 1e3:.3f}",
            "step_latency_ms": f"{latency * 1e3:.3f}", "budget_exhausted": str(result.budget_exhausted),
            "offset_cost": f"{result.offset_cost:.6g}", "avoidance_cost": f"{result.avoidance_cost:.6g}",
            "tracking_cost": f"{result.tracking_cost:.6g}", "y_a": str(result.y_a.tolist()),
            # the measured state (what the plant did); the plan starts from `planned_state`, it predicted
            # `predicted_delay_ms` ahead (core/sample/latency.py)
            "state": str((result.states[0] if result.measured_state is None else result.measured_state).tolist()),
            "planned_state": str(result.states[0].tolist()), "state_time": repr(state_time),
            "margin_unavoidable": str(result.margin_unavoidable),
            "fallback_reason": result.fallback_reason, "predicted_violation": f"{result.predicted_violation:.3g}",
            "region_unavoidable": str(result.region_unavoidable), "escape": result.escape,
            "fallback_predicted": json.dumps(result.fallback_predicted),  # candidate -> predicted violation
            "horizon": str(result.horizon),
            # the two phases (core/sample/feedback.py): the preparation ran between the samples, the feedback
            # gave the command; solve_time_ms counts both with the sample's own search
            "feedback": str(result.feedback or ""), "feedback_ms": f"{result.feedback_time * 1e3:.4f}",
            "preparation_ms": f"{result.preparation_time * 1e3:.3f}",
            # terminal: set (docs/terminal_set.md): V_f of the plan's x(N), alpha(y_a), x(N) in the set; nan, nan,
            # '' with the equality
            "terminal_cost": f"{result.terminal_cost:.6g}", "terminal_level": f"{result.terminal_level:.6g}",
            "terminal_inside": "" if result.terminal_inside is None else str(result.terminal_inside),
        })
    if cert is not None:
        values.update({"value_function": repr(cert.value_function), "decrease": repr(cert.decrease),
                       "decrease_bound": repr(cert.decrease_bound), "certificate_margin": repr(cert.margin),
                       "certificate_violations": str(cert.violations),
                       # the verdict as data (violated, held, not_checked); `certificate` renders it for people
                       "certificate_verdict": ("violated" if cert.violated else "held") if cert.checked
                       else "not_checked",
                       # what changed when the check restarted for changed parameters (JSON list)
                       "certificate_changed": json.dumps(list(cert.changed)),
                       "certificate": (("violated" if cert.violated else "checked") if cert.checked
                                       else f"not checked: {cert.reason}") + f"; V_N of the {cert.cost_source}"})
    status = DiagnosticStatus(level=level, name=f"{name}: nmpc", message=message, hardware_id=name)
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    msg = DiagnosticArray()
    msg.header.stamp = stamp
    msg.status = [status]
    return msg
