"""The plant's transforms for the views (nodes/plant.py): tf2_msgs is not among the PyPI wheels, so the
publishing path runs here against a stand-in tf2_msgs package written into the test's temp dir (on
sys.path for this test only) and a plant whose /tf and /tf_static publishers keep what they are given
(rclpy cannot publish a type without a generated type support). Everything else is the real node,
in-process on the test's DDS domain, advanced by calling its command callback (lockstep)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import TwistStamped
from rclpy.parameter import Parameter
from rosgraph import Probe
from std_msgs.msg import Float64MultiArray

from nmpc_avoid_ros.core.loop.closed_loop import ContinuousPlant
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.nodes import plant as plant_module
from nmpc_avoid_ros.ros.robot import yaw_of

FAKE_TF2_MSGS = '''
class TFMessage:
    """Stand-in of tf2_msgs/TFMessage: a list of geometry_msgs/TransformStamped."""

    def __init__(self, transforms=()):
        self.transforms = list(transforms)
'''


class Kept:
    """A publisher that keeps each message."""

    def __init__(self) -> None:
        self.messages: list = []

    def publish(self, msg) -> None:
        self.messages.append(msg)


class KeepingPlant(plant_module.PlantNode):
    """The plant node with its /tf, /tf_static publishers replaced by `Kept` ones."""

    def create_publisher(self, msg_type, topic, *args, **kwargs):
        if topic in ("/tf", "/tf_static"):
            self.kept = getattr(self, "kept", {})
            return self.kept.setdefault(topic, Kept())
        return super().create_publisher(msg_type, topic, *args, **kwargs)


@pytest.fixture
def fake_tf2_msgs(tmp_path, monkeypatch):
    package = tmp_path / "fake" / "tf2_msgs"
    (package / "msg").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "msg" / "__init__.py").write_text(FAKE_TF2_MSGS)
    monkeypatch.syspath_prepend(str(tmp_path / "fake"))
    for name in ("tf2_msgs", "tf2_msgs.msg"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    yield
    for name in ("tf2_msgs", "tf2_msgs.msg"):
        sys.modules.pop(name, None)


@pytest.fixture
def make_plant(ros_graph, tmp_path, monkeypatch):
    """make_plant(**parameters) -> an in-process plant on the test's domain, destroyed at the end."""
    monkeypatch.setenv("ROS_LOG_DIR", str(tmp_path))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    domain, _, _, _ = ros_graph
    probe = Probe(domain, "plant_tf_probe")
    nodes = []

    def make(**parameters):
        node = KeepingPlant(context=probe.context,
                            parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()])
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        node.destroy_node()
    probe.close()


def twist(v: float, omega: float) -> TwistStamped:
    msg = TwistStamped()
    msg.twist.linear.x, msg.twist.angular.z = v, omega
    return msg


def pose_of(transform) -> tuple[float, float, float]:
    t = transform.transform
    return t.translation.x, t.translation.y, yaw_of(t.rotation)


def test_the_import_guard_finds_tf2_msgs_only_where_it_is_importable(fake_tf2_msgs):
    sys.modules.pop("tf2_msgs.msg", None)
    assert plant_module.tf_message_type().__module__ == "tf2_msgs.msg"  # the stand-in


def test_the_unicycle_plant_publishes_odom_to_base_link_with_each_state(fake_tf2_msgs, make_plant):
    plant = make_plant(model="unicycle", interface="robot", lockstep=True, sample_time=0.2,
                       initial_state=[-4.0, -3.0, 0.5], base_frame="base_footprint")
    assert "/tf_static" not in plant.kept  # the controller draws in odom: no frame to alias
    plant.publish_state()  # x0, as once the controller listens
    commands = [(0.5, 0.0), (0.5, 1.0), (0.0, -2.0)]
    for v, omega in commands:
        plant.on_command(twist(v, omega))
    sent = plant.kept["/tf"].messages
    assert len(sent) == 1 + len(commands) and all(len(m.transforms) == 1 for m in sent)
    transforms = [m.transforms[0] for m in sent]
    assert {(t.header.frame_id, t.child_frame_id) for t in transforms} == {("odom", "base_footprint")}
    # stamped with the simulated time k Ts, as the odometry
    assert [t.header.stamp.sec + t.header.stamp.nanosec * 1e-9 for t in transforms] == \
        pytest.approx([0.0, 0.2, 0.4, 0.6])
    # the poses the continuous unicycle reaches
    x, sim = np.array([-4.0, -3.0, 0.5]), ContinuousPlant(make_model("unicycle"))
    expected = [x]
    for u in commands:
        x = sim.advance(x, np.array(u), 0.2)
        expected.append(x)
    for t, x in zip(transforms, expected):
        px, py, yaw = pose_of(t)
        assert (px, py) == pytest.approx((x[0], x[1]), abs=1e-9)
        assert math.remainder(yaw - x[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
        assert t.transform.translation.z == 0.0


def test_the_mobile_robot_plant_aliases_the_controller_frames_and_heads_where_it_moves(fake_tf2_msgs, make_plant):
    plant = make_plant(model="double_integrator_2d", lockstep=True, sample_time=0.25,
                       initial_state=[-8.0, -6.0, 0.0, 0.0])
    kept_odometry = plant.pub_odom = Kept()  # the odometry it publishes on `odom` as well
    (static,) = plant.kept["/tf_static"].messages
    assert [(t.header.frame_id, t.child_frame_id, pose_of(t)) for t in static.transforms] == \
        [("odom", "state", (0.0, 0.0, 0.0)), ("odom", "output", (0.0, 0.0, 0.0))]
    plant.publish_state()
    plant.on_command(Float64MultiArray(data=[0.0, 0.0]))  # at rest: the heading it had (0)
    plant.on_command(Float64MultiArray(data=[0.0, 1.0]))  # accelerates along +y
    plant.on_command(Float64MultiArray(data=[1.0, 0.0]))  # and turns towards +x
    poses = [pose_of(m.transforms[0]) for m in plant.kept["/tf"].messages]
    assert [p[2] for p in poses[:3]] == pytest.approx([0.0, 0.0, math.pi / 2])
    x = plant.x
    assert poses[3] == pytest.approx((x[0], x[1], math.atan2(x[3], x[2])))
    assert 0.0 < poses[3][2] < math.pi / 2
    # the odometry carries the same pose, the speed forward and the turn rate of the velocity
    odometry = kept_odometry.messages
    assert len(odometry) == 4 and {(o.header.frame_id, o.child_frame_id) for o in odometry} == {("odom", "base_link")}
    last = odometry[-1]
    assert (last.pose.pose.position.x, last.pose.pose.position.y, yaw_of(last.pose.pose.orientation)) == \
        pytest.approx(poses[3])
    assert last.twist.twist.linear.x == pytest.approx(math.hypot(x[2], x[3]))
    dt, sim = 1e-6, ContinuousPlant(make_model("double_integrator_2d"))
    ahead = sim.advance(x, plant.u, dt)
    turn_rate = math.remainder(math.atan2(ahead[3], ahead[2]) - math.atan2(x[3], x[2]), 2 * math.pi) / dt
    assert last.twist.twist.angular.z == pytest.approx(turn_rate, rel=1e-4)


def test_no_alias_frames_when_view_frames_is_emptied_and_no_tf_for_van_der_pol(fake_tf2_msgs, make_plant):
    plant = make_plant(model="double_integrator_2d", view_frames=[""])
    assert "/tf_static" not in plant.kept and "/tf" in plant.kept
    plant = make_plant(model="van_der_pol")
    assert getattr(plant, "kept", {}) == {} and plant.pub_odom is None
    plant = make_plant(model="unicycle", interface="robot", publish_tf=False)
    assert getattr(plant, "kept", {}) == {}


def test_the_plant_simulates_its_model_parameters_and_replay_builds_the_recorded_ones(make_plant):
    from nmpc_avoid_ros.bag.mcap_io import Bag
    from nmpc_avoid_ros.bag.node_parameters import RecordedSetup
    from nmpc_avoid_ros.core.config.settings import ControllerSettings
    from nmpc_avoid_ros.evaluation.counterfactual import _plant_choice

    longer = make_plant(model="bicycle", interface="robot", lockstep=True, sample_time=0.2,
                        model_parameters=["wheelbase=1.0"])
    default = make_plant(model="bicycle", interface="robot", lockstep=True, sample_time=0.2)
    assert (longer.model.parameters["wheelbase"], default.model.parameters["wheelbase"]) == (1.0, 0.5)
    setup = RecordedSetup(plant={"model": "bicycle", "integration": "continuous", "lockstep": False,
                                 "model_parameters": ["wheelbase=1.0"]}, plant_node="/plant")
    settings = ControllerSettings(model="bicycle")
    bag = Bag(path=Path("run.mcap"), topics={}, types={}, finished=True, files=[])
    assert _plant_choice(bag, setup, settings, None).make_model().parameters["wheelbase"] == 1.0
    assert _plant_choice(bag, RecordedSetup(), settings.replace(model_parameters=("wheelbase=0.8",)),
                         None).make_model().parameters["wheelbase"] == 0.8  # no plant recorded: the controller's
