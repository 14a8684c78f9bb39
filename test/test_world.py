"""A world to drive in (core/loop/world.py, nodes/plant_lidar.py): map_server maps and the simulated lidar."""

from __future__ import annotations

import math

import numpy as np
import pytest
from nav_msgs.msg import OccupancyGrid
from rclpy.qos import qos_profile_sensor_data
from rosgraph import ROOT
from sensor_msgs.msg import LaserScan

from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.core.loop.world import FREE, OCCUPIED, UNKNOWN, load_world, save_world
from nmpc_avoid_ros.core.perception.scan import Pose2D
from nmpc_avoid_ros.ros.parameters import LATCHED_QOS
from nmpc_avoid_ros.ros.perception import scan_ranges

WORLDS = sorted((ROOT / "config" / "worlds").glob("*.yaml"))
ROOM = ROOT / "config" / "worlds" / "room.yaml"


@pytest.mark.parametrize("path", [p for p in WORLDS if not p.stem.endswith("_walkers")], ids=lambda p: p.stem)
def test_each_shipped_world_is_a_walled_map_the_robot_starts_in(path):
    world = load_world(path)
    cells = world.grid.cells
    assert cells[0].min() == OCCUPIED and cells[-1].min() == OCCUPIED  # walled all round
    assert cells[:, 0].min() == OCCUPIED and cells[:, -1].min() == OCCUPIED
    assert not world.occupied(np.array([[-4.0, -3.0], [3.0, 2.0]])).any()  # the unicycle's start and goal are free


def test_the_lidar_sees_the_wall_and_a_walker_where_they_are():
    world = load_world(ROOM)  # 10 x 8 m from (-5, -4), 0.1 m walls; pillars away from y = 3
    sensor = Pose2D(0.0, 3.0, 0.0)
    angles = np.array([0.0, math.pi / 2, math.pi])
    ranges = world.scan(sensor, angles, range_max=8.0)
    # the inner faces of the walls: x = 4.9 ahead, y = 3.9 to the left (0.9 m), x = -4.9 behind
    assert ranges == pytest.approx([4.9, 0.9, 4.9], abs=world.grid.resolution / 2 + 1e-9)
    with_walker = world.scan(sensor, angles, range_max=8.0, circles=[(2.0, 3.0, 0.3)])
    assert with_walker[0] == pytest.approx(1.7, abs=1e-9) and with_walker[1:] == pytest.approx(ranges[1:])
    short = world.scan(sensor, angles, range_max=2.0)
    assert np.isinf(short[0]) and short[1] == pytest.approx(0.9, abs=0.03)  # beyond range_max: no return


def test_a_map_round_trips_through_its_files_with_unknown_cells(tmp_path):
    cells = np.full((20, 30), FREE, np.int8)
    cells[0, :] = OCCUPIED
    cells[5:8, 10:12] = UNKNOWN
    world = load_world(save_world(tmp_path / "m.yaml", cells, 0.1, (1.0, -2.0, 0.0)))
    assert np.array_equal(world.grid.cells, cells)
    assert world.grid.origin.x == 1.0 and world.grid.origin.y == -2.0 and world.grid.resolution == 0.1
    assert world.occupied(np.array([1.05, -1.95])) and not world.occupied(np.array([1.05, -1.85]))


@pytest.mark.parametrize("text, why", [
    ("image: m.pgm\nresolution: 0.1\n", "needs image, resolution and origin"),
    ("image: m.pgm\nresolution: -0.1\norigin: [0, 0, 0]\n", "resolution must be > 0"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, 0]\n", "origin [x, y, yaw]"),
    ("image: missing.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n", "cannot read its image"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nmode: scale\n", "trinary only"),
    ("image: [: bad", "cannot read it"),
])
def test_a_broken_map_file_is_refused_naming_the_file_and_the_fault(tmp_path, text, why):
    save_world(tmp_path / "m.yaml", np.zeros((4, 4), np.int8), 0.1)
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("m.pgm", str(tmp_path / "m.pgm")))
    with pytest.raises(ConfigError, match="bad.yaml") as info:
        load_world(bad)
    assert why in str(info.value)


@pytest.mark.dds
def test_the_plant_publishes_its_map_and_scans_of_it(ros_graph):
    """The unicycle's plant in the room: the latched map, and scans from its start pose (-4, -3, 0)."""
    _, _, start, probe = ros_graph
    p = probe()
    maps: list[OccupancyGrid] = []
    scans: list[LaserScan] = []
    p.node.create_subscription(OccupancyGrid, "map", maps.append, LATCHED_QOS)
    p.node.create_subscription(LaserScan, "scan", scans.append, qos_profile_sensor_data)
    plant = start("plant", "--ros-args", "--params-file", str(ROOT / "config" / "unicycle.yaml"),
                  "-p", f"world:={ROOM}", "-p", "lidar_beams:=360")
    assert p.spin_until(lambda: maps and len(scans) >= 3, 60), plant.output()
    assert (maps[0].info.width, maps[0].info.height) == (200, 160) and maps[0].header.frame_id == "odom"
    scan = scans[-1]
    ranges = scan_ranges(scan)
    assert len(ranges) == 360 and scan.header.frame_id == "base_link"
    # from (-4, -3) heading +x: the wall behind at x = -4.9 (0.9 m), the one below at y = -3.9 (0.9 m)
    behind, below = ranges[0], ranges[90]  # beam 0 points backwards (angle_min = -pi), beam 90 at -pi/2
    assert behind == pytest.approx(0.9, abs=0.03) and below == pytest.approx(0.9, abs=0.03)
    assert plant.stop() == 0
