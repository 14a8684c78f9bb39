"""The controller node's goal keeping (a mixin of ControllerNode, nodes/controller.py): the goal verdict of each
sample (core/loop/goal.py), the zero command while it holds, the latched `~/goal_reached` (std_msgs/Bool, transient
local: ControllerViews) and the verdict in /diagnostics (`goal_reached`, `goal_distance`, `goal_unreachable`,
`goal_unreachable_reason`, `goal_stop`).

Settings (NodeSettings, run-time): `goal_tolerance` (0: off, the default: no verdict, no values, the plan's
command), `goal_hysteresis`, `goal_rest_speed`. The sample is
still solved while the goal holds (the diagnostics, the certificate and the verdict go on; y_a is watched); only
its command is replaced by zeros, and the late cover is disarmed.
"""

from __future__ import annotations

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus

from ..core.loop.goal import GoalVerdict, GoalWatch
from ..core.sample.step_result import StepResult


class GoalKeeping:
    """ControllerNode's goal verdict; needs its `controller`, `options`, `state`, `target`, `lockstep`, `views`."""

    _goal_watch: GoalWatch | None = None
    goal_verdict = GoalVerdict()

    def goal_command(self, result: StepResult) -> tuple[np.ndarray, np.ndarray | None]:
        """(the command, the late cover's inputs) of this sample's `result`: zeros and none while the goal
        holds (reached, or settled where an unreachable goal leaves the robot), else the plan's."""
        verdict = self.observe_goal(result)
        if verdict.holds:
            return np.zeros(self.controller.model.m), None
        return result.u, None if self.lockstep else result.inputs[1:]

    def observe_goal(self, result: StepResult) -> GoalVerdict:
        """This sample's verdict (a new controller after a configure: a new watch); `~/goal_reached` on a change."""
        controller, options = self.controller, self.options
        if self._goal_watch is None or self._goal_watch.model is not controller.model:
            self._goal_watch = GoalWatch(controller.model)
        s = controller.settings
        margin = s.planning_margin + controller.mismatch_margin
        measured = self.state if result.measured_state is None else result.measured_state
        if options.goal_tolerance <= 0:  # off: nothing watched, nothing said
            self._goal_watch.reset()
            verdict = GoalVerdict(changed=self.goal_verdict.reached)
        else:
            verdict = self._goal_watch.observe(
                measured, self.target, result, [region.inflated(margin) for region in controller.regions], s.plane,
                s.output_plane, tolerance=options.goal_tolerance, hysteresis=options.goal_hysteresis,
                rest_speed=options.goal_rest_speed, time=self.state_time)
        if verdict.changed:
            self.views.publish_goal_reached(verdict.reached)
            self.get_logger().info(f"goal {self.target.tolist()} " + (
                f"reached ({verdict.distance:.3g} from it): zero command" if verdict.reached
                else f"left ({verdict.distance:.3g} from it): control resumes"))
        if verdict.unreachable and verdict.unreachable != self.goal_verdict.unreachable:
            self.get_logger().warning(verdict.note())
        self.goal_verdict = verdict
        return verdict

    def goal_values(self) -> dict[str, str]:
        """The last verdict as diagnostics values."""
        return self.goal_verdict.values()

    def goal_note(self, level: bytes, message: str) -> tuple[bytes, str]:
        """The sample's diagnostics level and message with the verdict: a reached goal says so; an unreachable one
        is at least WARN (never a plain ok while the robot stops short of its goal)."""
        note = self.goal_verdict.note()
        if not note:
            return level, message
        if self.goal_verdict.unreachable:
            level = max(level, DiagnosticStatus.WARN)
        return level, f"{message}; {note}"
