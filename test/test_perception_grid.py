"""Obstacles from an occupancy grid (core/perception/grid.py and the message conversions of ros/perception.py):
occupied cells in a window around the robot give a thin box along a wall and a circle around a pillar; a
grid whose resolution, size or data do not fit, or in an unknown frame, is refused with the reason."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import LaserScan

from nmpc_avoid_ros.core.errors import InputError
from nmpc_avoid_ros.core.perception.grid import Grid
from nmpc_avoid_ros.core.perception.scan import Pose2D
from nmpc_avoid_ros.core.perception.sensing import Perception, PerceptionSettings
from nmpc_avoid_ros.core.problem.shapes import Ellipse, Polygon, ellipse_g
from nmpc_avoid_ros.ros.perception import check_scan_frame, occupancy_grid, scan_geometry, scan_ranges

RESOLUTION = 0.05


def room_cells() -> np.ndarray:
    """10 m x 8 m at 5 cm from (-5, -4): a wall along y = 2 (x from -3 to 1), a 0.4 m pillar at (1.5, 0),
    a pillar at (4, -3) far from the robot, unknown cells along the bottom."""
    cells = np.zeros((160, 200), dtype=np.int8)
    cells[120:122, 40:120] = 100
    cells[76:84, 126:134] = 90
    cells[18:22, 178:182] = 100
    cells[0:10, :] = -1
    cells[40:44, 40:44] = 50  # below the occupied threshold: free enough
    return cells


def grid_of(origin: Pose2D = Pose2D(-5.0, -4.0, 0.0)) -> Grid:  # noqa: B008 - a frozen value
    cells = room_cells()
    return Grid.from_fields(cells.ravel(), cells.shape[1], cells.shape[0], RESOLUTION, origin)


def test_a_wall_and_a_pillar_within_the_window_give_a_thin_box_and_a_circle():
    seen = Perception(PerceptionSettings(half_window=3.5)).from_grid(grid_of(), Pose2D(0.0, 0.0, 0.0), 5.0)
    walls = [r for _, r in seen.regions if isinstance(r, Polygon)]
    circles = [r for _, r in seen.regions if isinstance(r, Ellipse)]
    (wall,) = walls
    xs, ys = np.asarray(wall.vertices).T
    # the cells cover x from -3 to 1, y from 2.0 to 2.1; each region covers its cells whole (half a cell's
    # diagonal, 3.5 cm, past the cell centres)
    assert ys.min() == pytest.approx(2.0, abs=0.015) and 2.1 <= ys.max() <= 2.2
    assert xs.min() == pytest.approx(-3.0, abs=0.1) and xs.max() == pytest.approx(1.0, abs=0.1)
    assert xs.min() <= -3.0 and xs.max() >= 1.0
    (pillar,) = circles  # the far pillar at (4, -3) lies outside the 3.5 m window
    # the 0.4 m square pillar: its circumscribed circle (0.283 m) and at most a few cm more
    assert math.dist(pillar.center, (1.5, 0.0)) < 0.01 and 0.2828 <= pillar.semi_axes[0] <= 0.32


def test_a_rotated_grid_places_its_cells_by_its_origin_pose():
    yaw = 0.7
    origin = Pose2D(1.0, -2.0, yaw).compose(Pose2D(-5.0, -4.0, 0.0))  # the same map, turned about (1, -2)
    seen = Perception(PerceptionSettings(half_window=8.0)).from_grid(grid_of(origin), Pose2D(1.0, -2.0, 0.0), 0.0)
    turned = Pose2D(1.0, -2.0, yaw).apply(np.array([[1.5, 0.0]]))[0]
    assert min(math.dist(r.center, turned) for _, r in seen.regions if isinstance(r, Ellipse)) < 0.05


def test_a_robot_outside_the_grid_sees_nothing_and_nothing_fails():
    seen = Perception().from_grid(grid_of(), Pose2D(100.0, 100.0, 0.0), 0.0)
    assert seen.regions == () and seen.points == 0


@pytest.mark.parametrize(("fields", "reason"), [
    ({"resolution": 0.0}, "resolution"),
    ({"resolution": -0.05}, "resolution"),
    ({"resolution": math.nan}, "resolution"),
    ({"resolution": 1e9}, "resolution"),
    ({"width": 199}, "data has 32000 cells"),
    ({"width": 0}, "size must be positive"),
    ({"height": -160}, "size must be positive"),
    ({"width": 10**6, "height": 10**6}, "at most"),
])
def test_a_grid_whose_fields_do_not_fit_is_refused_with_the_reason(fields, reason):
    cells = room_cells()
    given = {"width": 200, "height": 160, "resolution": RESOLUTION, **fields}
    with pytest.raises(InputError, match=reason):
        Grid.from_fields(cells.ravel(), given["width"], given["height"], given["resolution"], Pose2D())


def grid_message(frame: str = "map") -> OccupancyGrid:
    msg = OccupancyGrid()
    msg.header.frame_id = frame
    msg.info.resolution, msg.info.width, msg.info.height = RESOLUTION, 200, 160
    msg.info.origin.position.x, msg.info.origin.position.y = -5.0, -4.0
    msg.info.origin.orientation.w = 1.0
    msg.data = room_cells().ravel().tolist()
    return msg


def test_grid_messages_in_an_unknown_frame_or_with_a_broken_origin_are_refused():
    grid = occupancy_grid(grid_message(), ("odom", "map"))
    assert grid.cells.shape == (160, 200) and grid.cells[121, 50] == 100 and grid.cells[0, 0] == -1
    with pytest.raises(InputError, match="frame_id is 'world'"):
        occupancy_grid(grid_message("world"), ("odom", "map"))
    with pytest.raises(InputError, match="frame_id is 'map'"):
        occupancy_grid(grid_message(), ("odom", ""))  # no map frame configured: odom only
    msg = grid_message()
    msg.info.origin.orientation.w = 0.0
    with pytest.raises(InputError, match="zero norm"):
        occupancy_grid(msg, ("map",))
    msg = grid_message()
    msg.info.origin.position.x = math.inf
    with pytest.raises(InputError, match="origin must be finite"):
        occupancy_grid(msg, ("map",))


def test_scan_messages_convert_without_a_loop_and_their_frame_is_checked_when_asked():
    msg = LaserScan()
    msg.header.frame_id = "base_scan"
    msg.angle_min, msg.angle_max, msg.angle_increment = -1.0, 1.0, 0.5
    msg.range_min, msg.range_max = 0.1, 10.0
    msg.ranges = [1.0, math.nan, math.inf, 2.5, 3.0]
    ranges = scan_ranges(msg)
    assert ranges.dtype == float and ranges[0] == 1.0 and math.isnan(ranges[1]) and ranges[3] == 2.5
    scan_geometry(msg).check(len(ranges))
    check_scan_frame(msg, "")
    check_scan_frame(msg, "base_scan")
    with pytest.raises(InputError, match="expected 'laser'"):
        check_scan_frame(msg, "laser")


@st.composite
def grids(draw) -> tuple[np.ndarray, int, int]:
    """Cells (percent, -1 unknown) of a random width x height grid; now and then one cell short or over."""
    width, height = draw(st.integers(1, 30)), draw(st.integers(1, 30))
    size = width * height + draw(st.sampled_from([0, 0, 0, 0, -1, 1]))
    cells = draw(st.lists(st.sampled_from([-1, 0, 0, 0, 30, 70, 100, 100]), min_size=size, max_size=size))
    return np.asarray(cells, dtype=np.int8), width, height


@settings(max_examples=80, deadline=None)
@given(grid_fields=grids(), resolution=st.floats(0.01, 0.5), yaw=st.floats(-4.0, 4.0), x=st.floats(-3.0, 3.0),
       y=st.floats(-3.0, 3.0))
def test_any_grid_is_refused_with_a_reason_or_every_occupied_cell_in_the_window_lies_in_a_region(
        grid_fields, resolution, yaw, x, y):
    cells, width, height = grid_fields
    try:
        grid = Grid.from_fields(cells, width, height, resolution, Pose2D(-1.0, -1.0, yaw))
    except InputError as exc:
        assert len(cells) != width * height and "cells" in str(exc)
        return
    settings = PerceptionSettings(max_circles=10**4, max_walls=10**4, half_window=2.0)
    seen = Perception(settings).from_grid(grid, Pose2D(x, y, 0.0), 0.0)
    regions = [r for _, r in seen.regions]
    centres = grid.occupied_points(np.array([x, y]), 2.0, settings.occupied_threshold)
    assert seen.points == len(centres)
    # the whole cell, its corners too, lies in a region
    corners = np.concatenate([centres + Pose2D(0.0, 0.0, yaw).apply(np.array([[dx, dy]]) * resolution)
                              for dx in (-0.5, 0.5) for dy in (-0.5, 0.5)])
    if len(corners):
        deepest = np.max([depths(r, corners) for r in regions], axis=0)
        assert deepest.min() >= -1e-6, corners[np.argmin(deepest)]


def depths(region: Ellipse | Polygon, points: np.ndarray) -> np.ndarray:
    """g of the region at points [K, 2] (> 0 inside), vectorised: Ellipse.depth and Polygon.depth, many at once."""
    if isinstance(region, Ellipse):
        return ellipse_g(points.T, region.slot_values())
    planes = region.half_planes()
    return np.min(planes[:, 2] - points @ planes[:, :2].T, axis=1)
