"""launch/world.launch.py through DDS: the unicycle reaches its goal in each shipped world, seeing only what its
simulated lidar sees (plant with the world's map and walkers -> scan -> `obstacles` node -> regions -> controller).

The nodes are started as `ros2 launch` would start them (test_launch_files.py reads the launch file with
stand-in launch modules), in real time.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import yaml
from nav_msgs.msg import Odometry
from rosgraph import ROOT
from scipy.spatial import cKDTree
from std_msgs.msg import Bool
from test_launch_files import Resolver, load_launch, nodes_of

from nmpc_avoid_ros.core.loop.world import OCCUPIED, load_world
from nmpc_avoid_ros.ros.parameters import LATCHED_QOS, STREAM_QOS

# serial: clearance in real time, alone on the machine. In a CI run beside the other DDS tests the unicycle's body came
# 0.204 m from a pillar cell's centre (into the half cell) and then stood there: every fallback candidate predicted a
# violation and the stop won (now after N such samples the summed violation ranks: docs/design.md, 'Fallback').
# Beside two or three busy loops here, 17 of 18 runs kept 0.282-0.444 m and one came to 0.202: an unpredicted delay
# of a starved machine
pytestmark = [pytest.mark.dds, pytest.mark.slow, pytest.mark.serial]

GOAL = (3.0, 2.0)  # config/unicycle_world.yaml's target
REACH_WITHIN = 60.0  # s of real time (the room took 13-15 s here)
#: m, each config's footprint_radius
BODY = {"unicycle_world.yaml": 0.2, "bicycle_world.yaml": 0.25}


def wall_distance(world_file: str, xy: np.ndarray) -> float:
    """The least distance (m) from the robot's positions [K, 2] to an occupied cell's centre."""
    grid = load_world(world_file).grid
    rows, cols = np.nonzero(grid.cells >= OCCUPIED)
    centres = grid.origin.apply(np.column_stack([cols + 0.5, rows + 0.5]) * grid.resolution)
    return float(cKDTree(centres).query(xy)[0].min())


@pytest.mark.parametrize("world, walkers, config", [
    ("worlds/room.yaml", "worlds/room_walkers.yaml", "unicycle_world.yaml"),
    ("worlds/pillars.yaml", "", "unicycle_world.yaml"),
    ("worlds/room.yaml", "worlds/room_walkers.yaml", "bicycle_world.yaml")], ids=["room", "pillars", "car-room"])
# the car (config/bicycle_world.yaml, its steering at most 1.5 rad/s): 0.338-0.385 m from a wall cell's centre in 12
# of 12 runs, alone, beside two busy loops and on an empty solver cache (docs/campaign/bicycle_world/README.md). With
# the limit and before a fallback applied the input it was judged by, 3 of 7 runs came into a wall
def test_the_robots_reach_their_goal_in_the_shipped_worlds(ros_graph, monkeypatch, world, walkers, config):
    _, _, start, probe = ros_graph
    p = probe()
    poses: list[tuple[float, float]] = []
    reached: list[bool] = []
    p.node.create_subscription(Odometry, "odom", lambda m: poses.append((m.pose.pose.position.x,
                                                                         m.pose.pose.position.y)), STREAM_QOS)
    p.node.create_subscription(Bool, "controller/goal_reached", lambda m: reached.append(m.data), LATCHED_QOS)
    description = load_launch(ROOT / "launch" / "world.launch.py", monkeypatch)
    resolve = Resolver(description)
    resolve.defaults.update(world=world, walkers=walkers, config=str(ROOT / "config" / config))
    procs = []
    for node in nodes_of(description):
        kw = node.kwargs
        args = ["--ros-args", "-r", f"__node:={kw['name']}"]
        for item in kw["parameters"]:
            if isinstance(item, dict):
                for key, value in item.items():
                    args += ["-p", f"{key}:={yaml.safe_dump(resolve(value), default_flow_style=True).strip()}"]
            else:
                args += ["--params-file", resolve(item)]
        procs.append(start(kw["executable"], *args))
    begin = time.monotonic()
    ok = p.spin_until(lambda: any(reached), REACH_WITHIN + 60.0)  # + the nodes' start
    took = time.monotonic() - begin
    xy = np.array(poses)
    outputs = [proc.output()[-2000:] for proc in procs]
    assert ok, (xy[-1:] if len(xy) else None, outputs)
    assert np.hypot(xy[-1, 0] - GOAL[0], xy[-1, 1] - GOAL[1]) <= 0.15
    # the body (footprint_radius) clear of the walls and pillars: its centre at least the body's radius from every
    # occupied cell's face (half a cell from its centre)
    distance = wall_distance(world, xy)
    print(f"{config} in {world}: goal reached {took:.1f} s after the start, least distance to a wall cell's centre "
          f"{distance:.3f} m (body {BODY[config]} m + half a cell 0.025 m)")
    assert distance >= BODY[config] + 0.025, distance
    assert all(proc.stop() == 0 for proc in procs), outputs
