"""The shipped RViz and Foxglove layouts against the running nodes of the robot config each belongs to,
through real DDS (docs/usage.md, "RViz and Foxglove"); the plant's word on tf where tf2_msgs is missing;
and the controller's "obstacles received" line, once per change of the obstacle set."""

from __future__ import annotations

import importlib
import json
import re
from collections import defaultdict
from pathlib import Path

import pytest
import yaml
from rclpy.qos import QoSPresetProfiles, qos_profile_sensor_data
from rosgraph import CONFIG, ROOT
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import MarkerArray

from nmpc_avoid_ros.core.config.settings import load_params_file
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse
from nmpc_avoid_ros.nodes.plant import PLANT_SPECS, tf_message_type
from nmpc_avoid_ros.ros.markers import regions_to_markers
from nmpc_avoid_ros.ros.parameters import LATCHED_QOS, STREAM_QOS

pytestmark = [pytest.mark.dds, pytest.mark.slow]

#: the robot configs and their views (config/*.rviz, config/*.foxglove.json)
LAYOUTS = {"unicycle.yaml": ("unicycle.rviz", "unicycle.foxglove.json"),
           # the robot interface's topics and frames: the unicycle's views fit the car-like robot as they are
           "bicycle.yaml": ("unicycle.rviz", "unicycle.foxglove.json"),
           "mobile_robot.yaml": ("mobile_robot.rviz", "mobile_robot.foxglove.json"),
           "mobile_robot_live.yaml": ("mobile_robot.rviz", "mobile_robot.foxglove.json"),
           "unicycle_world.yaml": ("world.rviz", "world.foxglove.json"),
           "bicycle_world.yaml": ("world.rviz", "world.foxglove.json")}
RVIZ_TYPES = {"rviz_default_plugins/Odometry": "nav_msgs/msg/Odometry",
              "rviz_default_plugins/Path": "nav_msgs/msg/Path",
              "rviz_default_plugins/MarkerArray": "visualization_msgs/msg/MarkerArray",
              "rviz_default_plugins/Marker": "visualization_msgs/msg/Marker",
              "rviz_default_plugins/TwistStamped": "geometry_msgs/msg/TwistStamped",
              "rviz_default_plugins/SetGoal": "geometry_msgs/msg/PoseStamped",
              "rviz_default_plugins/Map": "nav_msgs/msg/OccupancyGrid",
              "rviz_default_plugins/LaserScan": "sensor_msgs/msg/LaserScan",
              "rviz_default_plugins/Polygon": "geometry_msgs/msg/PolygonStamped"}
#: the QoS a view reads a type with where the stream's reliable volatile one does not match: scans are sent
#: best effort (sensor data), the map and the footprint once, latched
VIEW_QOS = {"sensor_msgs/msg/LaserScan": qos_profile_sensor_data, "nav_msgs/msg/OccupancyGrid": LATCHED_QOS,
            "geometry_msgs/msg/PolygonStamped": LATCHED_QOS}
#: what the views send to the controller (the goal tool) or show as sent to it: subscribed by it
SENT_TO_CONTROLLER = {"/goal_pose", "/obstacles"}
DEFAULT_VIEW_FRAMES = next(s.default for s in PLANT_SPECS if s.name == "view_frames")
NO_TF = "tf2_msgs is not importable"


def rviz_topics(path: Path) -> tuple[str, dict[str, str]]:
    """(fixed frame, {topic: type}) of an RViz config: its displays (also in groups) and tools."""
    manager = yaml.safe_load(path.read_text())["Visualization Manager"]
    topics = {}

    def walk(items: list[dict]) -> None:
        for item in items:
            walk(item.get("Displays", []))
            if "Topic" in item:
                topics[item["Topic"]["Value"]] = RVIZ_TYPES[item["Class"]]

    walk(manager["Displays"] + manager["Tools"])
    return manager["Global Options"]["Fixed Frame"], topics


def foxglove_topics(path: Path) -> tuple[set[str], dict[str, str], list[tuple[str, str]]]:
    """(follow frames, {topic: type or ''}, [(topic, message path)]) of a Foxglove layout."""
    frames, topics, paths = set(), {}, []
    for config in json.loads(path.read_text())["configById"].values():
        if "followTf" in config:
            frames.add(config["followTf"])
        for topic in config.get("topics", {}):
            topics.setdefault(topic, "")
        if "publish" in config:
            topics[config["publish"]["poseTopic"]] = "geometry_msgs/msg/PoseStamped"
        for entry in config.get("paths", []):
            topic, field = entry["value"].split(".", 1)
            topics.setdefault(topic, "")
            paths.append((topic, field))
        if "topicPath" in config:
            topics.setdefault(config["topicPath"], "")
    return frames, topics, paths


def message_type(name: str) -> type:
    package, _, msg = name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), msg)


def field_of(msg, path: str):
    """The value at a Foxglove message path (`twist.linear.x`, `data[3]`); IndexError past an array's end."""
    value = msg
    for part in path.split("."):
        name, _, index = part.partition("[")
        value = getattr(value, name)
        if index:
            value = value[int(index[:-1])]
    return value


def frames_of(msg) -> set[str]:
    """The frames a message is drawn in (a MarkerArray's DELETEALL has none)."""
    if isinstance(msg, MarkerArray):
        return {m.header.frame_id for m in msg.markers if m.header.frame_id}
    return {msg.header.frame_id} if hasattr(msg, "header") else set()


def test_every_robot_config_has_its_views_and_every_view_belongs_to_one():
    shipped = {p.name for p in (ROOT / "config").iterdir() if p.suffix == ".rviz" or "foxglove" in p.name}
    claimed = {name for pair in LAYOUTS.values() for name in pair}
    assert shipped == claimed, shipped ^ claimed
    robots = {p.name for p in (ROOT / "config").glob("*.yaml")
              if make_model(load_params_file(p).section("controller").get("model", "van_der_pol")).planar is not None}
    assert robots == set(LAYOUTS)
    # the two mobile robot configs share their views: the same model and interface, so the same topics
    mobile = [load_params_file(ROOT / "config" / name).section("controller") for name in LAYOUTS if "mobile" in name]
    assert len({(c["model"], c.get("interface", "array")) for c in mobile}) == 1


# the world's lockstep loop never started twice (no command in 240 s; once alone): probably x0 published before
# the controller's reader had matched the plant's writer, now published after the readers stayed matched 0.5 s
# (nodes/plant.py INITIAL_SETTLE); still alone on the machine
@pytest.mark.parametrize("config", ["unicycle.yaml", "mobile_robot_live.yaml",
                                    pytest.param("unicycle_world.yaml", marks=pytest.mark.serial)])
def test_the_views_of_a_robot_config_match_its_running_nodes(ros_graph, config):
    """Lockstep plant and controller of the config, a target and an obstacle: every topic the RViz
    config and the Foxglove layout name exists with the type they expect, published by the nodes (what
    the views send: subscribed by the controller); every plotted field is in the messages that arrive;
    everything drawn is in the fixed frame, or in a frame the plant relates to it on tf (base_link;
    on the array interface `state` and `output`, as odom itself); the odometry, which places the robot,
    is in the fixed frame itself, so it needs no tf."""
    _, _, start, probe = ros_graph
    p = probe()
    rviz, foxglove = (ROOT / "config" / name for name in LAYOUTS[config])
    fixed, rviz_types = rviz_topics(rviz)
    follow, fox_types, paths = foxglove_topics(foxglove)
    assert follow == {fixed} == {"odom"}
    wanted = {**fox_types, **rviz_types}
    robot = load_params_file(ROOT / "config" / config).section("controller").get("interface") == "robot"
    command = "/cmd_vel" if robot else "/command"
    assert {"/odom", "/controller/prediction", "/controller/regions", "/obstacles"} <= set(rviz_types)
    assert {"/odom", "/controller/prediction", "/controller/regions", "/controller/certificate", command} <= \
        set(fox_types)
    assert (command in rviz_types) == robot  # RViz draws no Float64MultiArray (the mobile robot's command)

    # the probe reads the plant's state before the nodes start: the lockstep plant waits for it and the controller
    heard: dict[str, list] = defaultdict(list)
    state_topic, state_type = ("/odom", "nav_msgs/msg/Odometry") if robot else \
        ("/state", "std_msgs/msg/Float64MultiArray")
    p.node.create_subscription(message_type(state_type), state_topic, heard[state_topic].append, STREAM_QOS)
    states = heard[state_topic]
    target = p.node.create_publisher(Float64MultiArray, "target", LATCHED_QOS)
    obstacles = p.node.create_publisher(MarkerArray, "obstacles", LATCHED_QOS)
    params = ["--ros-args", "--params-file", str(ROOT / "config" / config), "-p", "lockstep:=true"]
    ctrl = start("controller", *params)
    plant = start("plant", *params, "-p", "wait_for_subscribers:=2", "-p", "max_steps:=20")

    def graph() -> dict[str, list[str]]:
        return dict(p.node.get_topic_names_and_types())

    sent = {t for t in wanted if t in SENT_TO_CONTROLLER}
    assert p.spin_until(lambda: set(wanted) - sent <= set(graph()), 180), \
        (set(wanted) - set(graph()), ctrl.output()[-3000:], plant.output()[-2000:])
    types = graph()
    for topic in set(wanted) - sent - {state_topic}:
        (type_name,) = types[topic]
        p.node.create_subscription(message_type(type_name), topic, heard[topic].append,
                                   VIEW_QOS.get(type_name, STREAM_QOS))
    # an obstacle beside the straight line, in the frame the config's markers are in; then the target,
    # which starts the loop (the lockstep controller idles without one)
    marker_frame = "odom" if robot else "output"
    markers = regions_to_markers([Ellipse((-2.0, -0.5), (0.6, 0.6), 0.0, "output")])
    for marker in markers.markers:
        marker.header.frame_id = marker.header.frame_id and marker_frame
    obstacles.publish(markers)
    p.spin_for(2.0)  # the probe's readers matched
    target.publish(Float64MultiArray(data=[3.0, 2.0]))
    drawn = set(wanted) - sent - {"/diagnostics"}
    assert p.spin_until(lambda: len(states) >= 21 and all(heard[t] for t in drawn)
                        and any(frames_of(m) for m in heard["/controller/regions"]), 240), \
        ({t for t in drawn if not heard[t]}, len(states), ctrl.output()[-3000:])

    types = graph()
    for topic, expected in wanted.items():
        assert topic in types, topic
        assert not expected or expected in types[topic], (topic, types[topic])
        if topic in SENT_TO_CONTROLLER:
            readers = {i.node_name for i in p.node.get_subscriptions_info_by_topic(topic)}
            assert "controller" in readers, (topic, readers)
        else:
            writers = {i.node_name for i in p.node.get_publishers_info_by_topic(topic)}
            assert writers & {"controller", "plant"}, (topic, writers)
    for topic, field in paths:
        assert isinstance(field_of(heard[topic][-1], field), float), (topic, field)
    frames = {topic: set().union(*(frames_of(m) for m in heard[topic])) for topic in drawn}
    assert frames["/odom"] == {fixed}
    related = {fixed, "base_link"} | (set() if robot else set(DEFAULT_VIEW_FRAMES))
    assert set().union(*frames.values()) <= related, frames
    if not robot:
        assert frames["/controller/prediction"] == {"state"} and frames["/controller/regions"] == {"output"}
    if tf_message_type() is None:
        # without tf2_msgs: said once, and no /tf
        assert plant.output().count(NO_TF) == 1 and "/tf" not in types, plant.output()
    else:
        assert NO_TF not in plant.output() and "tf2_msgs/msg/TFMessage" in types["/tf"]
    assert plant.stop() == 0 and ctrl.stop() == 0


def test_obstacles_received_is_logged_once_per_change_of_the_set_not_per_message(ros_graph):
    """The same MarkerArray 20 times: one "obstacles received" line; a marker more: one line more; the
    same two markers moving (new poses, the same ns/id) 5 times: none. log_throttle 0, so the line
    is not merely throttled."""
    _, _, start, probe = ros_graph
    p = probe()
    diags = p.diagnostics_of("/controller")
    ctrl = start("controller", "--ros-args", "--params-file", str(CONFIG), "-p", "log_throttle:=0.0")
    publisher = p.node.create_publisher(MarkerArray, "obstacles", QoSPresetProfiles.DEFAULT.value)
    assert p.spin_until(lambda: publisher.get_subscription_count() >= 1, 60), ctrl.output()
    assert p.heard_by("controller", 60), ctrl.output()

    def received() -> int:
        return int(diags[-1].get("obstacles_received", 0)) if diags else 0

    def lines() -> int:
        return len(re.findall(r"obstacles received: \d+ region\(s\) stored", ctrl.output()))

    def send(regions, times: int) -> None:
        before = received()
        msg = regions_to_markers(regions)
        for _ in range(times):
            publisher.publish(msg)
            p.spin_for(0.1)
        assert p.spin_until(lambda: received() >= before + times, 30), (received(), before, ctrl.output()[-2000:])

    one = [Ellipse((0.0, 1.0), (0.5, 0.5), 0.0, "state")]
    send(one, 20)
    assert received() == 20 and lines() == 1, ctrl.output()
    two = [*one, Ellipse((2.0, -1.0), (0.4, 0.4), 0.0, "state")]
    send(two, 1)
    assert lines() == 2, ctrl.output()
    for k in range(5):  # a moving feed: the same keys, new poses
        send([Ellipse((0.1 * k, 1.0), (0.5, 0.5), 0.0, "state"), two[1]], 1)
    assert received() == 26 and lines() == 2, ctrl.output()
    assert "obstacles received: 2 region(s) stored" in ctrl.output()
    assert ctrl.stop() == 0
