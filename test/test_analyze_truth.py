"""`analyze` tells the truth from the bag: the recorded plant states, targets per segment, the settings it recorded.

The bags are written here with the package's own MCAP writer (no ROS graph), with diagnostics as the
controller publishes them and states, commands, targets and goals as the plant and `send` do, so every
expected number is known exactly.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, TwistStamped
from nav_msgs.msg import Odometry
from std_msgs.msg import Float64MultiArray

from nmpc_avoid_ros.bag.distance import signed_distance
from nmpc_avoid_ros.bag.mcap_writer import Ros2McapWriter
from nmpc_avoid_ros.bag.node_parameters import PARAMETERS_RECORD, parameters_record
from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
from nmpc_avoid_ros.core.loop.metrics import keep_in_values
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse, rotated_box
from nmpc_avoid_ros.ros.markers import regions_to_markers
from nmpc_avoid_ros.ros.robot import yaw_of, yaw_quaternion
from nmpc_avoid_ros.tools.analyze import main as analyze_main

CONFIG = default_config_path().parent
TS = 0.5  # s, the van der Pol configs' sample time
PER_SAMPLE = 10  # plant states per sample (20 Hz)
NS = 10**9
T0 = 100 * NS  # the clock of the recording starts here (ns)

# x1 at the samples: target 5 for samples 0..9 (overshoot to 5.5, settled from sample 6),
# target -3 from sample 10 (overshoot to -3.6, settled from sample 15 = 5 after the change)
X1 = [-5.0, -2.0, 1.0, 4.0, 5.5, 5.2, 5.0, 5.0, 5.0, 5.0,
      5.0, 2.0, -1.0, -3.6, -3.1, -3.0, -3.0, -3.0, -3.0, -3.0]


def _settings_fields(settings: ControllerSettings) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(settings).items()}


def _sample(state, command, y_a, state_time, node="/controller", **extra: str) -> DiagnosticArray:
    values = {"state": str(list(state)), "command": str(list(command)), "y_a": str(list(y_a)), "solve_time_ms": "5.0",
              "status": "ok", "state_time": repr(state_time), **extra}
    status = DiagnosticStatus(name=f"{node}: nmpc", hardware_id=node,
                              values=[KeyValue(key=k, value=v) for k, v in values.items()])
    return DiagnosticArray(status=[status])


def _vdp_states() -> list[np.ndarray]:
    """The plant's 20 Hz states: [x1(k), 0] at the samples; between samples 2 and 3 x2 = 0.55 while x1
    goes from 1 to 4 (|x1 x2| up to 3.7 * 0.55 = 2.035), between 11 and 12 one state at [-0.1, 2.097]."""
    states = []
    for k in range(len(X1)):
        states.append(np.array([X1[k], 0.0]))
        if k + 1 == len(X1):
            break
        for j in range(1, PER_SAMPLE):
            x1 = X1[k] + (X1[k + 1] - X1[k]) * j / PER_SAMPLE
            x2 = 0.55 if k == 2 else (2.097 if (k, j) == (11, 7) else 0.0)
            states.append(np.array([x1, x2]))
    return states


def _vdp_bag(path, *, records=True, refused=True, phases=False):
    """The van der Pol live config's run of X1 (module doc): targets 5 then -3 and, with `refused`, a
    wrong-size target [5, 0] the controller refused; one command beyond the input box (6.3)."""
    settings = ControllerSettings.from_params(load_params_file(CONFIG / "van_der_pol_live.yaml").section("controller"))
    states = _vdp_states()
    with Ros2McapWriter(path) as bag:
        if records:
            bag.add_metadata(PARAMETERS_RECORD, parameters_record(
                "/controller", {**_settings_fields(settings), "interface": "array", "target": None}, 0))
        bag.write_message("/target", Float64MultiArray(data=[5.0]), T0 - NS)
        if refused:
            bag.write_message("/target", Float64MultiArray(data=[5.0, 0.0]), T0 + 2 * NS)
        bag.write_message("/target", Float64MultiArray(data=[-3.0]), T0 + int(9.9 * TS * NS))
        step = TS / PER_SAMPLE
        for j, x in enumerate(states):
            bag.write_message("/state", Float64MultiArray(data=x.tolist()), T0 + round(j * step * NS))
        for k, x1 in enumerate(X1):
            t = T0 + round(k * TS * NS)
            # u = x1 holds [x1, 0] still: the re-simulation sees no excursion; the plant got 6.3 once
            bag.write_message("/command", Float64MultiArray(data=[6.3] if k == 3 else [x1]), t + 2 * 10**6)
            # with `phases`: the first sample searched, then every third one (its prepared plan refused), the rest
            # answered by the prepared plan in (k + 1) * 0.01 ms after a 20 ms preparation
            extra = {} if not phases else {"feedback": "" if k == 0 else "inputs_changed" if k % 3 == 0 else "answered",
                                           "feedback_ms": f"{0.0 if k % 3 == 0 else (k + 1) * 0.01:.4f}",
                                           "preparation_ms": "0.000" if k == 0 else "20.000"}
            bag.write_message("/diagnostics", _sample([x1, 0.0], [x1], [x1], t * 1e-9, **extra), t + 3 * 10**6)
    return settings, states


@pytest.fixture(scope="module")
def vdp_metrics(tmp_path_factory):
    folder = tmp_path_factory.mktemp("vdp")
    _vdp_bag(folder / "live.mcap")
    assert analyze_main([str(folder / "live.mcap"), "--out", str(folder / "o")]) == 0
    (metrics,) = json.loads((folder / "o" / "metrics.json").read_text())["bags"]
    return metrics, folder


def test_the_recorded_states_between_the_samples_are_the_truth_and_analyze_reports_their_maximum(vdp_metrics):
    metrics, _ = vdp_metrics
    states = np.array(_vdp_states())
    worst = float(np.max(np.abs(states[:, 0] * states[:, 1])))
    assert worst == pytest.approx(3.7 * 0.55) and worst > 2.03
    clearance = metrics["clearance"]
    truth = clearance["recorded_states"]
    assert truth["topic"] == "/state" and truth["states"] == len(states)
    assert truth["rate_hz"] == pytest.approx(20.0)
    assert truth["max_abs_x1x2"] == worst  # exactly the recorded maximum
    # the keep-in |x1 x2| <= 2 as the config writes it: x1*x2 - 2 <= 0 and -x1*x2 - 2 <= 0
    first = next(k for k in truth["keep_in"] if k["expression"].startswith("x1*x2"))
    assert first["max_g"] == pytest.approx(worst - 2.0, abs=1e-12)
    assert first["states_outside"] == sum(1 for x in states if x[0] * x[1] > 2.0)
    assert truth["max_penetration_keep_in"] == max(max(k["max_g"] for k in truth["keep_in"]), 0.0)
    assert first["time"] == pytest.approx(2 * TS + 9 * TS / PER_SAMPLE)
    # the samples and the re-simulation (u = x1 holds [x1, 0] still) see none of it, and say which they are
    assert clearance["at_samples"]["max_penetration"] == 0.0 and clearance["at_samples"]["max_abs_x1x2"] == 0.0
    assert clearance["resimulated_between_samples"]["max_penetration"] == pytest.approx(0.0, abs=1e-9)
    assert "max_penetration" not in metrics and "between_samples" not in metrics


def test_state_and_input_box_excursions_come_from_the_recorded_states_and_commands(vdp_metrics):
    metrics, _ = vdp_metrics
    box = metrics["state_box"]
    assert box["max_excursion"] == pytest.approx(0.097, abs=1e-12) and box["coordinate"] == "x2"
    assert box["outside"] == 1 and box["time"] == pytest.approx(11 * TS + 7 * TS / PER_SAMPLE)
    assert box["per_coordinate"]["x1"] == 0.0
    inputs = metrics["input_box"]
    assert inputs["source"] == "/command" and inputs["commands"] == len(X1)
    assert inputs["max_excursion"] == pytest.approx(0.3, abs=1e-12) and inputs["coordinate"] == "u"


def test_targets_5_then_minus_3_are_two_segments_and_a_refused_target_is_skipped(vdp_metrics):
    metrics, folder = vdp_metrics
    first, second = metrics["segments"]
    assert (first["target"], first["start_step"], first["end_step"]) == ([5.0], 0, 10)
    assert (second["target"], second["start_step"], second["end_step"]) == ([-3.0], 10, 20)
    # the first: settled at sample 6 (3 s), overshoot 0.5 of a step of 10
    assert first["settling_step"] == 6 and first["settling_time"] == 3.0
    assert first["overshoot"] == pytest.approx(0.05)
    # the second, from its own change: settled 5 samples (2.5 s) later, overshoot 0.6 of a step of 8
    assert second["settling_step"] == 5 and second["settling_time"] == 2.5 and second["settled_at_step"] == 15
    assert second["overshoot"] == pytest.approx(0.075) and second["start_time"] == 5.0
    assert second["final_error"] == 0.0
    # the run settled on its last target at sample 15
    assert metrics["settling_step"] == 15 and metrics["settling_time"] == 7.5
    assert metrics["overshoot"] == pytest.approx(0.075) and metrics["target"] == [-3.0]
    # the wrong-size target was refused by the controller: not a target, listed with the reason
    (refused,) = metrics["targets_refused"]
    assert refused["topic"] == "/target" and "expected 1 values, got 2" in refused["reason"]
    assert metrics["targets_accepted"] == 2
    # the recorded states per segment: the excursion belongs to the first target
    assert first["max_penetration"] == pytest.approx(3.7 * 0.55 - 2.0, abs=1e-12)
    # the second's recorded states (from sample 10's on) hold [-0.1, 2.097]: inside |x1 x2| <= 2, outside a keep-in
    # |x2| <= 2 where the config has one
    settings = ControllerSettings.from_params(load_params_file(CONFIG / "van_der_pol_live.yaml").section("controller"))
    later = np.array(_vdp_states()[10 * PER_SAMPLE:])
    g = keep_in_values(settings, make_model("van_der_pol"), later, np.zeros((len(later), 1)))
    assert second["max_penetration"] == max(0.0, float(np.max(g)))
    assert second["recorded_states"] == len(later) and first["recorded_states"] == 10 * PER_SAMPLE
    assert (folder / "o" / "time_series.png").stat().st_size > 10_000


def test_the_settings_are_the_recorded_ones_and_metrics_json_names_their_source(vdp_metrics, tmp_path, capsys):
    metrics, _ = vdp_metrics
    config = metrics["config"]
    assert config["source"] == "the bag's /controller parameters" and config["controller_node"] == "/controller"
    assert config["closest_shipped"] == {"file": "config/van_der_pol_live.yaml", "differs_in": []}
    # an old bag without the parameters: the shipped van_der_pol.yaml, and it says so
    _vdp_bag(tmp_path / "old.mcap", records=False)
    assert analyze_main([str(tmp_path / "old.mcap"), "--out", str(tmp_path / "o")]) == 0
    assert "assumed: the bag holds no usable controller parameters" in capsys.readouterr().err
    (old,) = json.loads((tmp_path / "o" / "metrics.json").read_text())["bags"]
    assert old["config"]["source"].startswith("assumed") and "van_der_pol.yaml" in old["config"]["source"]
    assert old["config"]["closest_shipped"] == {"file": "config/van_der_pol.yaml", "differs_in": []}
    assert old["clearance"]["recorded_states"]["max_abs_x1x2"] == metrics["clearance"]["recorded_states"][
        "max_abs_x1x2"]


GOALS = [(3.0, 0.0), (3.0, 2.0)]


def _odometry(x, y, theta, frame="odom") -> Odometry:
    msg = Odometry()
    msg.header.frame_id, msg.child_frame_id = frame, "base_link"
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(x), float(y)
    msg.pose.pose.orientation = yaw_quaternion(theta)
    return msg


def _goal(x, y, frame="odom") -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = frame
    msg.pose.position.x, msg.pose.position.y = float(x), float(y)
    msg.pose.orientation.w = 1.0
    return msg


def _robot_bag(path):
    """A unicycle run through the robot interface, goals on goal_pose only (no /target): along y = 0.8 past a
    circle of radius 0.5 at (1, 0) (closest 0.3 m) to (3, 0.8), then up to (3, 2); a goal in the
    wrong frame (refused); an obstacle box in the odom frame."""
    settings = ControllerSettings.from_params(load_params_file(CONFIG / "unicycle.yaml").section("controller"))
    ts = settings.sample_time
    circle, box = Ellipse((1.0, 0.0), (0.5, 0.5), frame="output"), rotated_box((2.0, 6.0), (1.0, 1.0), frame="output")
    path_xy = [(-1.0 + 0.5 * k, 0.8) for k in range(9)] + [(3.0, 0.8 + 0.3 * k) for k in range(1, 5)] + [(3.0, 2.0)] * 6
    with Ros2McapWriter(path) as bag:
        bag.add_metadata(PARAMETERS_RECORD, parameters_record(
            "/controller", {**_settings_fields(settings), "interface": "robot", "odom_frame": "odom"}, 0))
        markers = regions_to_markers([circle, box])
        for marker in markers.markers:
            marker.header.frame_id = "odom"
        bag.write_message("/obstacles", markers, T0 - NS)
        bag.write_message("/goal_pose", _goal(*GOALS[0]), T0 - NS // 2)
        bag.write_message("/goal_pose", _goal(9.0, 9.0, frame="map"), T0 + NS)
        bag.write_message("/goal_pose", _goal(*GOALS[1]), T0 + round(8.5 * ts * NS))
        for k, (x, y) in enumerate(path_xy):
            t = T0 + round(k * ts * NS)
            theta = 0.0 if k < 9 else math.pi / 2
            for j, frac in enumerate((0.0, 0.5)):  # the plant at twice the sample rate
                nxt = path_xy[min(k + 1, len(path_xy) - 1)]
                px, py = x + (nxt[0] - x) * frac, y + (nxt[1] - y) * frac
                bag.write_message("/odom", _odometry(px, py, theta), t + round(j * ts / 2 * NS))
            state = [x, y, yaw_of(yaw_quaternion(theta))]  # what the controller reads from the odometry
            u = [0.8 if k < len(path_xy) - 6 else 0.0, 0.0]
            bag.write_message("/cmd_vel", TwistStamped(twist=_twist(*u)), t + 2 * 10**6)
            bag.write_message("/diagnostics", _sample(state, u, [x, y], t * 1e-9), t + 3 * 10**6)
    return settings, circle, box


def _twist(v, omega):
    from geometry_msgs.msg import Twist

    twist = Twist()
    twist.linear.x, twist.angular.z = float(v), float(omega)
    return twist


def test_a_robot_bag_with_goals_on_goal_pose_and_no_target_is_analysed_per_goal_in_metres(tmp_path):
    _robot_bag(tmp_path / "robot.mcap")
    assert analyze_main([str(tmp_path / "robot.mcap"), "--out", str(tmp_path / "o")]) == 0
    (metrics,) = json.loads((tmp_path / "o" / "metrics.json").read_text())["bags"]
    assert metrics["model"] == "unicycle" and metrics["config"]["interface"] == "robot"
    assert metrics["config"]["closest_shipped"] == {"file": "config/unicycle.yaml", "differs_in": []}
    assert "max_abs_x1x2" not in metrics["clearance"]["at_samples"]
    assert "max_abs_x1x2" not in metrics["clearance"]["recorded_states"]
    first, second = metrics["segments"]
    assert first["target"] == list(GOALS[0]) and second["target"] == list(GOALS[1])
    assert second["start_step"] == 9 and second["settling_step"] == 3 and second["settled_at_step"] == 12
    (refused,) = metrics["targets_refused"]
    assert refused["topic"] == "/goal_pose" and "'map'" in refused["reason"]
    # clearance in metres: the path passes 0.3 m from the circle (at x = 1), the box is far
    truth = metrics["clearance"]["recorded_states"]
    assert truth["topic"] == "/odom" and truth["states"] == 2 * 19
    assert truth["min_obstacle_distance"] == pytest.approx(0.3, abs=1e-12)
    assert first["min_obstacle_distance"] == pytest.approx(0.3, abs=1e-12)
    assert second["min_obstacle_distance"] == pytest.approx(math.hypot(2.0, 1.1) - 0.5, abs=1e-12)  # from (3, 1.1)
    assert metrics["clearance"]["units"]["obstacle_distance_output"] == "m"
    # the normalised g beside it: 1 - r^2 / 0.25 at r = 0.8
    assert truth["min_clearance_obstacles"] == pytest.approx(0.8**2 / 0.25 - 1.0, abs=1e-12)
    assert metrics["input_box"]["source"] == "/cmd_vel" and metrics["input_box"]["max_excursion"] == 0.0
    assert (tmp_path / "o" / "phase_portrait.png").stat().st_size > 10_000


def test_a_four_state_robot_bag_is_analysed_with_its_own_model(tmp_path):
    """The mobile robot (double integrator, 4 states) on the array interface: no van der Pol output evaluated;
    its target is the controller's `target` parameter (no message)."""
    settings = ControllerSettings.from_params(load_params_file(CONFIG / "mobile_robot_live.yaml").section("controller"))
    path = tmp_path / "mobile.mcap"
    with Ros2McapWriter(path) as bag:
        bag.add_metadata(PARAMETERS_RECORD, parameters_record(
            "/controller", {**_settings_fields(settings), "target": [1.0, 0.0], "constraints": ["vx <= 0.5"]}, 0))
        for k in range(8):
            x = [min(0.25 * k, 1.0), 0.0, 1.0 if k < 4 else 0.0, 0.0]
            t = T0 + round(k * settings.sample_time * NS)
            bag.write_message("/state", Float64MultiArray(data=x), t)
            bag.write_message("/diagnostics", _sample(x, [0.0, 0.0], x[:2], t * 1e-9), t + 3 * 10**6)
    assert analyze_main([str(path), "--out", str(tmp_path / "o")]) == 0
    (metrics,) = json.loads((tmp_path / "o" / "metrics.json").read_text())["bags"]
    assert metrics["model"] == "double_integrator_2d" and metrics["segments"][0]["target"] == [1.0, 0.0]
    assert metrics["segments"][0]["settling_step"] == 4 and "max_abs_x1x2" not in metrics["clearance"]["at_samples"]
    assert metrics["config"]["closest_shipped"]["file"] == "config/mobile_robot_live.yaml"
    # the keep-in vx^2 + vy^2 <= 1.44 on the recorded states: 1 - 1.44 at most
    (speed,) = metrics["clearance"]["recorded_states"]["keep_in"]
    assert speed["max_g"] == pytest.approx(1.0 - 1.44)
    # a hard constraint of Z the bag's settings name, on the recorded states too: vx = 1 at the first four
    (hard,) = metrics["clearance"]["recorded_states"]["constraints"]
    assert (hard["expression"], hard["max_g"], hard["states_outside"]) == ("vx <= 0.5", pytest.approx(0.5), 4)


@pytest.mark.parametrize("point, expected", [
    ((3.0, 0.0), 1.0), ((0.0, 2.0), 1.0), ((0.0, 0.0), -1.0), ((2.0, 0.5), None), ((0.5, 0.2), None)])
def test_signed_distance_to_an_ellipse_is_the_euclidean_one(point, expected):
    ellipse = Ellipse((0.0, 0.0), (2.0, 1.0), yaw=0.0)
    angles = np.linspace(0.0, 2 * np.pi, 200_001)
    boundary = np.column_stack([2.0 * np.cos(angles), np.sin(angles)])
    brute = float(np.min(np.linalg.norm(boundary - np.asarray(point), axis=1)))
    inside = (point[0] / 2.0) ** 2 + point[1] ** 2 < 1
    assert signed_distance(ellipse, point) == pytest.approx(-brute if inside else brute, abs=1e-8)
    if expected is not None:
        assert signed_distance(ellipse, point) == pytest.approx(expected, abs=1e-12)
    # rotated and moved: the same distance
    turned = Ellipse((1.0, -2.0), (2.0, 1.0), yaw=0.7)
    c, s = math.cos(0.7), math.sin(0.7)
    moved = (1.0 + c * point[0] - s * point[1], -2.0 + s * point[0] + c * point[1])
    assert signed_distance(turned, moved) == pytest.approx(signed_distance(ellipse, point), abs=1e-9)


def test_the_two_phases_are_reported_where_the_bag_has_them(vdp_metrics, tmp_path):
    """feedback_ms of the samples the prepared plan answered, the preparations (core/sample/feedback.py); an older
    bag, without them, has no such metric."""
    metrics, _ = vdp_metrics
    assert "feedback" not in metrics
    _vdp_bag(tmp_path / "phases.mcap", phases=True)
    assert analyze_main([str(tmp_path / "phases.mcap"), "--out", str(tmp_path / "o")]) == 0
    (metrics,) = json.loads((tmp_path / "o" / "metrics.json").read_text())["bags"]
    answered = [k for k in range(len(X1)) if k % 3]
    assert metrics["feedback"]["answered"] == len(answered) and metrics["feedback"]["prepared"] == len(X1) - 1
    assert metrics["feedback"]["feedback_ms"]["median"] == pytest.approx(np.median([(k + 1) * 0.01 for k in answered]))
    assert metrics["feedback"]["preparation_ms"]["median"] == pytest.approx(20.0)


@pytest.mark.parametrize("config", sorted(p.name for p in CONFIG.glob("*.yaml")))
def test_analyze_and_its_html_report_run_on_a_bag_of_every_shipped_config(tmp_path, config):
    """Every shipped params file: a short run recorded as its nodes publish it (the plant's initial state moving
    slowly, zero commands, the scenario's target on `target`, or as a goal on `goal_pose` for the robot
    interface), analysed with the HTML report: its own model and config recognised, no error."""
    params = load_params_file(CONFIG / config)
    section = params.section("controller")
    settings = ControllerSettings.from_params(section)
    robot = section.get("interface") == "robot"
    model = make_model(settings.model)
    x0 = np.array(params.section("plant").get("initial_state", np.zeros(model.n)), float)
    target = [float(v) for v in params.section("scenario")["target"]]
    u = np.zeros(model.m)
    ts = settings.sample_time
    path = tmp_path / "run.mcap"
    with Ros2McapWriter(path) as bag:
        bag.add_metadata(PARAMETERS_RECORD, parameters_record(
            "/controller", {**_settings_fields(settings), "interface": section.get("interface", "array")}, 0))
        if robot:
            bag.write_message("/goal_pose", _goal(*target[:2]), T0 - NS // 2)
        else:
            bag.write_message("/target", Float64MultiArray(data=target), T0 - NS // 2)
        for k in range(6):
            x = x0.copy()
            x[0] += 0.05 * k
            t = T0 + round(k * ts * NS)
            y = np.asarray(model.output(x, u), float).ravel()
            if robot:
                bag.write_message("/odom", _odometry(x[0], x[1], x[2]), t)
                bag.write_message("/cmd_vel", TwistStamped(twist=_twist(0.0, 0.0)), t + 2 * 10**6)
            else:
                bag.write_message("/state", Float64MultiArray(data=x.tolist()), t)
                bag.write_message("/command", Float64MultiArray(data=u.tolist()), t + 2 * 10**6)
            bag.write_message("/diagnostics", _sample(x.tolist(), u.tolist(), y.tolist(), t * 1e-9), t + 3 * 10**6)
    out = tmp_path / "o"
    assert analyze_main([str(path), "--out", str(out), "--html", str(out / "report.html")]) == 0
    (metrics,) = json.loads((out / "metrics.json").read_text())["bags"]
    assert metrics["model"] == settings.model and metrics["samples"] == 6
    assert metrics["config"]["interface"] == ("robot" if robot else "array")
    assert metrics["config"]["closest_shipped"]["file"] == f"config/{config}"
    assert metrics["segments"][0]["target"] == target[: len(metrics["segments"][0]["target"])]
    assert ("max_abs_x1x2" in metrics["clearance"]["at_samples"]) == (settings.model == "van_der_pol")
    assert (out / "report.html").stat().st_size > 10_000
