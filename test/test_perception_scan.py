"""Obstacles from a laser scan (core/perception): a synthetic room with a round obstacle gives a circle at its
place and thin boxes along the walls; tracks keep their ids and measure a walker's velocity; bad scans are
refused with a reason or cleaned, the last good regions kept; property-based: whatever the ranges, a scan is
refused with an InputError or every usable return lies in a region."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nmpc_avoid_ros.core.errors import InputError
from nmpc_avoid_ros.core.perception.fitting import cluster_labels
from nmpc_avoid_ros.core.perception.raycast import cast, room
from nmpc_avoid_ros.core.perception.scan import MAX_BEAMS, Pose2D, ScanGeometry, scan_points
from nmpc_avoid_ros.core.perception.sensing import Perception, PerceptionSettings
from nmpc_avoid_ros.core.problem.shapes import Ellipse, Polygon

BEAMS = 720
INCREMENT = 2 * math.pi / BEAMS
GEOMETRY = ScanGeometry(-math.pi, -math.pi + INCREMENT * (BEAMS - 1), INCREMENT, 0.05, 30.0)
ANGLES = GEOMETRY.angle_min + INCREMENT * np.arange(BEAMS)
ROOM = room(4.0, 3.0)  # walls at x = +-4, y = +-3 (m)
MANY = PerceptionSettings(max_circles=20, max_walls=20)


def scan_of(robot: Pose2D, circles=((1.5, 0.8, 0.3),), laser: Pose2D | None = None) -> np.ndarray:
    return cast(robot.compose(laser or Pose2D()), ANGLES, ROOM, circles, GEOMETRY.range_max)


def circles_of(regions) -> list[Ellipse]:
    return [r for _, r in regions if isinstance(r, Ellipse)]


def test_a_room_with_a_round_obstacle_gives_a_circle_at_its_place_and_thin_boxes_along_the_walls():
    robot = Pose2D(-1.0, -0.5, 0.3)
    seen = Perception(MANY).from_scan(scan_of(robot), GEOMETRY, robot, 1.0)
    assert seen.points == BEAMS and seen.not_finite == 0
    # the obstacle (radius 0.3 at (1.5, 0.8)): the nearest circle, within a few mm (a noise-free arc)
    nearest = min(circles_of(seen.regions), key=lambda e: math.dist(e.center, (1.5, 0.8)))
    assert math.dist(nearest.center, (1.5, 0.8)) < 0.01 and nearest.semi_axes[0] == pytest.approx(0.3, abs=0.01)
    # the wall y = -3 (in front of the robot's right): a thin box whose near face is the wall, along x
    walls = [r for _, r in seen.regions if isinstance(r, Polygon)]
    lower = [w for w in walls if np.ptp(np.asarray(w.vertices)[:, 0]) > 3.0 and max(y for _, y in w.vertices) < -2.5]
    assert len(lower) == 1, walls
    ys = np.asarray(lower[0].vertices)[:, 1]
    assert ys.max() == pytest.approx(-3.0, abs=0.02) and ys.min() == pytest.approx(-3.1, abs=0.02)
    xs = np.asarray(lower[0].vertices)[:, 0]
    assert xs.min() < -3.9 and xs.max() > 3.9  # the whole wall from corner to corner
    # every wall is found (a box reaching to within 2 cm of each of the four faces)
    for axis, value in ((0, -4.0), (0, 4.0), (1, -3.0), (1, 3.0)):
        assert any(np.min(np.abs(np.asarray(w.vertices)[:, axis] - value)) < 0.02 for w in walls), (axis, value)


def test_a_laser_offset_from_base_link_places_the_returns_where_they_are():
    robot, laser = Pose2D(0.5, 1.0, -2.0), Pose2D(0.3, -0.1, 0.2)
    settings = PerceptionSettings(max_circles=20, max_walls=20, laser_offset=laser)
    seen = Perception(settings).from_scan(scan_of(robot, laser=laser), GEOMETRY, robot, 0.0)
    assert min(math.dist(e.center, (1.5, 0.8)) for e in circles_of(seen.regions)) < 0.01


def test_the_nearest_regions_fill_the_slots():
    robot = Pose2D(-1.0, -0.5, 0.3)
    seen = Perception(PerceptionSettings(max_circles=1, max_walls=2)).from_scan(scan_of(robot), GEOMETRY, robot, 0.0)
    kinds = [type(r).__name__ for _, r in seen.regions]
    assert kinds.count("Ellipse") == 1 and kinds.count("Polygon") == 2
    # the wall y = -3 is the nearest (2.5 m), then x = -4 (3 m): they fill the two wall slots
    near_faces = sorted(round(float(np.min(np.abs(np.asarray(r.vertices)).max(axis=1))), 1)
                        for _, r in seen.regions if isinstance(r, Polygon))
    assert len(near_faces) == 2


def test_tracks_keep_their_ids_and_a_walker_gets_its_velocity_within_ten_percent():
    perception = Perception(MANY)
    robot, velocity = Pose2D(-2.0, -1.0, 0.0), np.array([0.5, -0.3])
    ids_of_walls = None
    for k in range(10):
        t = 0.1 * k
        walker = np.array([1.0, 1.5]) + velocity * t
        seen = perception.from_scan(scan_of(robot, circles=((*walker, 0.3),)), GEOMETRY, robot, 100.0 + t)
        walls = {i for i, r in seen.regions if isinstance(r, Polygon)}
        ids_of_walls = walls if ids_of_walls is None else ids_of_walls
        # the walls keep their ids (the walker's shadow may split one: the new part gets a new id)
        assert ids_of_walls <= walls
    (track_id, moving), = [(i, r) for i, r in seen.regions if isinstance(r, Ellipse) and r.moving]
    assert np.linalg.norm(np.subtract(moving.velocity, velocity)) <= 0.1 * np.linalg.norm(velocity)
    assert moving.stamp == pytest.approx(100.9) and math.dist(moving.center, walker) < 0.01
    # the walls and the corners are static: velocity exactly zero, as the controller packs them once
    assert all(not r.moving for i, r in seen.regions if i != track_id)


def test_a_stamp_going_back_restarts_the_tracks():
    perception, robot = Perception(MANY), Pose2D(-2.0, -1.0, 0.0)
    for stamp, x in ((1.0, 1.0), (1.1, 1.05), (0.5, 1.1)):
        seen = perception.from_scan(scan_of(robot, circles=((x, 1.5, 0.3),)), GEOMETRY, robot, stamp)
    assert not any(r.moving for _, r in seen.regions)  # no velocity from a replayed (older) scan


@pytest.mark.parametrize(("speed", "yaw_rate"), [(1.0, 0.0), (0.8, 0.5), (0.5, -2.0), (0.0, 1.0)])
def test_a_pose_moves_along_the_exact_arc_of_its_twist(speed, yaw_rate):
    start, dt = Pose2D(1.0, -2.0, 0.4), 0.7
    steps, pose = 20000, start  # the unicycle integrated in small Euler steps
    h = dt / steps
    for _ in range(steps):
        pose = Pose2D(pose.x + speed * math.cos(pose.yaw) * h, pose.y + speed * math.sin(pose.yaw) * h,
                      pose.yaw + yaw_rate * h)
    moved = start.moved(speed, yaw_rate, dt)
    assert (moved.x, moved.y, moved.yaw) == pytest.approx((pose.x, pose.y, pose.yaw), abs=1e-4)
    back = moved.moved(speed, yaw_rate, -dt)
    assert (back.x, back.y, back.yaw) == pytest.approx((start.x, start.y, start.yaw), abs=1e-12)


def test_a_full_turn_closes_the_chain_and_neighbouring_beams_link():
    # a ring of returns around the sensor (a round room, 2 m): one cluster across the first and last beam
    points = 2.0 * np.column_stack([np.cos(ANGLES), np.sin(ANGLES)])
    assert cluster_labels(points, 0.25, ordered=True, closed=True)[0] == 1
    # not closed (a scan of less than a turn): linked only along the beams, split where the beams end
    assert cluster_labels(points, 0.25, ordered=True, closed=False)[0] == 1
    assert cluster_labels(points[::-1][:400], 0.25, ordered=True)[0] == 1
    gap = np.delete(points, range(100, 110), axis=0)  # ten beams without a return: still one object (0.17 m)
    assert cluster_labels(gap, 0.25, ordered=True, closed=True)[0] == 1
    far = np.delete(points, range(100, 130), axis=0)  # thirty (0.52 m): the ring opens, still one chain
    assert cluster_labels(far, 0.25, ordered=True, closed=True)[0] == 1
    two = np.delete(points, [*range(100, 130), *range(400, 430)], axis=0)  # two gaps: two arcs
    assert cluster_labels(two, 0.25, ordered=True, closed=True)[0] == 2
    assert cluster_labels(two, 0.25, ordered=True, closed=False)[0] == 3  # the seam at the first beam too


def test_nan_and_infinite_ranges_are_dropped_and_counted():
    robot = Pose2D(-1.0, -0.5, 0.3)
    ranges = scan_of(robot)
    ranges[::7] = np.nan
    ranges[3::11] = np.inf
    ranges[5::13] = -np.inf
    ranges[1::17] = 0.01  # below range_min
    seen = Perception(MANY).from_scan(ranges, GEOMETRY, robot, 0.0)
    assert seen.not_finite == np.count_nonzero(~np.isfinite(ranges)) > 100
    assert seen.out_of_range == np.count_nonzero(ranges == 0.01)
    assert min(math.dist(e.center, (1.5, 0.8)) for e in circles_of(seen.regions)) < 0.02


@pytest.mark.parametrize(("changes", "beams", "reason"), [
    ({"angle_increment": 0.0}, BEAMS, "angle_increment must be non-zero"),
    ({"angle_increment": INCREMENT / 2}, BEAMS, "give"),
    ({"angle_max": math.pi / 2}, BEAMS, "give"),
    ({}, BEAMS + 5, "give"),
    ({"range_min": 0.0}, BEAMS, "range_min must be > 0"),
    ({"range_min": -1.0}, BEAMS, "range_min must be > 0"),
    ({"range_max": 0.0}, BEAMS, "range_max must exceed"),
    ({"range_min": 5.0, "range_max": 5.0}, BEAMS, "range_max must exceed"),
    ({"angle_min": math.nan}, BEAMS, "finite"),
    ({"angle_increment": math.inf}, BEAMS, "finite"),
    ({}, MAX_BEAMS + 1, f"more than {MAX_BEAMS}"),
])
def test_a_scan_that_cannot_be_placed_is_refused_with_its_reason_and_the_last_regions_stay(changes, beams, reason):
    robot = Pose2D(-1.0, -0.5, 0.3)
    perception = Perception(MANY)
    good = perception.from_scan(scan_of(robot), GEOMETRY, robot, 0.0)
    fields = {k: getattr(GEOMETRY, k) for k in ("angle_min", "angle_max", "angle_increment", "range_min",
                                               "range_max")}
    bad = ScanGeometry(**{**fields, **changes})
    with pytest.raises(InputError, match=reason):
        perception.from_scan(np.full(beams, 2.0), bad, robot, 0.1)
    assert perception.last is good and perception.tracker.last_stamp == 0.0


def test_a_clockwise_scan_and_a_driver_that_counts_one_beam_less_are_accepted():
    robot = Pose2D(-1.0, -0.5, 0.3)
    reverse = ScanGeometry(math.pi - INCREMENT, -math.pi, -INCREMENT, 0.05, 30.0)
    ranges = cast(robot, reverse.angle_min + reverse.angle_increment * np.arange(BEAMS), ROOM, ((1.5, 0.8, 0.3),))
    seen = Perception(MANY).from_scan(ranges, reverse, robot, 0.0)
    assert min(math.dist(e.center, (1.5, 0.8)) for e in circles_of(seen.regions)) < 0.01
    scan_points(np.ones(BEAMS - 1), GEOMETRY, robot)  # angle_max one increment past the last beam


def test_a_scan_of_noise_costs_what_its_nearest_clusters_do():
    """100000 beams (the most accepted) of random ranges: ~100000 one-return clusters, the nearest 200 fitted."""
    increment = 2 * math.pi / MAX_BEAMS
    geometry = ScanGeometry(-math.pi, -math.pi + increment * (MAX_BEAMS - 1), increment, 0.05, 30.0)
    ranges = np.random.default_rng(3).uniform(0.1, 30.0, MAX_BEAMS)
    perception = Perception()
    start = time.perf_counter()
    seen = perception.from_scan(ranges, geometry, Pose2D(), 0.0)
    assert time.perf_counter() - start < 2.0  # 0.035 s measured; every cluster fitted (max_clusters 1e6): 249 s
    assert len(seen.regions) == 6 and seen.points == MAX_BEAMS  # the nearest 6 circles, no wall in noise


def test_a_wall_seen_at_a_grazing_angle_stays_one_object_with_the_adaptive_breakpoint():
    """A 1-degree lidar 1 m from a long wall, beams 12 to 90 degrees off it: its returns spread to 0.4 m apart
    4.7 m along it (78 degrees off the wall's normal; lambda = 10 degrees links up to 80)."""
    robot = Pose2D(0.0, 0.0, 0.0)
    angles = np.radians(np.arange(12.0, 91.0, 1.0))
    ranges = cast(robot, angles, [(-1.0, 1.0, 20.0, 1.0)])  # the wall y = 1, x from -1 to 20
    geometry = ScanGeometry(float(angles[0]), float(angles[-1]), math.radians(1.0), 0.05, 30.0)
    points = scan_points(ranges, geometry, robot).points
    fixed = cluster_labels(points, 0.25, ordered=True, sensor=robot.position, breakpoint_angle=0.0)[0]
    adaptive = cluster_labels(points, 0.25, ordered=True, sensor=robot.position, breakpoint_angle=math.radians(10))[0]
    assert fixed >= 3 and adaptive == 1
    walls = [r for _, r in Perception().from_scan(ranges, geometry, robot, 0.0).regions if isinstance(r, Polygon)]
    assert len(walls) == 1 and max(x for x, _ in walls[0].vertices) > 4.6


def test_clusters_are_single_linkage_at_the_gap():
    points = np.array([[0.0, 0.0], [0.2, 0.0], [0.4, 0.0], [1.0, 0.0], [1.1, 0.05]])
    count, labels = cluster_labels(points, 0.25)
    assert count == 2 and len(set(labels[:3])) == 1 and labels[3] == labels[4] != labels[0]
    assert cluster_labels(np.zeros((0, 2)), 0.25)[0] == 0
    assert cluster_labels(np.array([[0.0, 0.0], [5.0, 5.0]]), 0.25)[0] == 2


not_finite = st.sampled_from([math.nan, math.inf, -math.inf])
finite_or_not = st.one_of(st.floats(-1.0, 40.0), not_finite)


def _covered(ranges: list[float], geometry: ScanGeometry, robot: Pose2D) -> None:
    """The scan is refused with a reason (nothing else raised), or every usable return lies in a region."""
    perception = Perception(PerceptionSettings(max_circles=1000, max_walls=1000))
    try:
        seen = perception.from_scan(np.asarray(ranges), geometry, robot, 0.0)
    except InputError as exc:
        assert str(exc) and perception.last is None
        return
    points = scan_points(np.asarray(ranges), geometry, robot).points
    assert seen.points == len(points) and seen.not_finite + seen.out_of_range + seen.points == len(ranges)
    regions = [r for _, r in seen.regions]
    for p in points:
        assert max(r.depth(p) for r in regions) >= -1e-6, p


@settings(max_examples=150, deadline=None)
@given(ranges=st.lists(finite_or_not, max_size=300),
       angle_min=st.one_of(st.floats(-4.0, 4.0), not_finite),
       increment=st.one_of(st.just(INCREMENT), st.just(-INCREMENT), st.floats(-0.2, 0.2), not_finite),
       range_min=st.one_of(st.floats(-1.0, 1.0), not_finite), range_max=st.one_of(st.floats(-1.0, 40.0), not_finite),
       exact_span=st.booleans(), x=st.floats(-5.0, 5.0), yaw=st.floats(-7.0, 7.0))
def test_any_scan_is_refused_with_a_reason_or_every_usable_return_lies_in_a_region(
        ranges, angle_min, increment, range_min, range_max, exact_span, x, yaw):
    angle_max = angle_min + increment * (len(ranges) - 1) if exact_span else angle_min + 1.0
    _covered(ranges, ScanGeometry(angle_min, angle_max, increment, range_min, range_max), Pose2D(x, 0.0, yaw))


@settings(max_examples=100, deadline=None)
@given(ranges=st.lists(finite_or_not, min_size=1, max_size=400), angle_min=st.floats(-4.0, 4.0),
       fraction=st.floats(0.01, 1.0), clockwise=st.booleans(), range_min=st.floats(0.01, 1.0),
       reach=st.floats(0.1, 40.0), x=st.floats(-5.0, 5.0), yaw=st.floats(-7.0, 7.0))
def test_every_usable_return_of_a_well_formed_scan_lies_in_a_region(
        ranges, angle_min, fraction, clockwise, range_min, reach, x, yaw):
    increment = (-1 if clockwise else 1) * fraction * 2 * math.pi / len(ranges)
    geometry = ScanGeometry(angle_min, angle_min + increment * (len(ranges) - 1), increment, range_min,
                            range_min + reach)
    geometry.check(len(ranges))  # well formed: never refused
    _covered(ranges, geometry, Pose2D(x, 0.0, yaw))


def square(center: tuple[float, float], half: float) -> list[tuple[float, float, float, float]]:
    """The four sides of an axis-aligned square pillar as segments."""
    (cx, cy), h = center, half
    corners = [(cx - h, cy - h), (cx + h, cy - h), (cx + h, cy + h), (cx - h, cy + h)]
    return [(*corners[i], *corners[(i + 1) % 4]) for i in range(4)]


@pytest.mark.parametrize("robot", [Pose2D(0.0, 0.0, 0.0), Pose2D(0.0, -2.0, 0.7), Pose2D(1.0, 0.5, 0.0)])
def test_a_square_pillar_seen_from_one_side_gets_a_circle_about_the_whole_pillar(robot):
    """Face-on the returns lie on a line (no arc to fit): the pillar is taken as deep as it is wide."""
    pillar, half = (2.0, 0.5), 0.2
    ranges = cast(robot, ANGLES, square(pillar, half), range_max=GEOMETRY.range_max)
    seen = Perception().from_scan(ranges, GEOMETRY, robot, 0.0)
    (circle,) = [r for _, r in seen.regions if isinstance(r, Ellipse)]
    corners = [(pillar[0] + dx, pillar[1] + dy) for dx in (-half, half) for dy in (-half, half)]
    # the back corners too, within a beam's spacing (the last return falls short of a corner by up to 1.7 cm)
    assert all(math.dist(c, circle.center) <= circle.semi_axes[0] + 0.02 for c in corners), circle
    assert math.dist(circle.center, pillar) < 0.01 and circle.semi_axes[0] <= half * math.sqrt(2) + 0.01


def test_a_static_pillar_passed_by_a_moving_robot_stays_static():
    perception = Perception()
    for k in range(30):  # the robot passes at 1 m/s, 10 scans a second, from 1.5 m before to 1.5 m past it
        robot = Pose2D(0.5 + 0.1 * k, -0.5, 0.0)
        ranges = cast(robot, ANGLES, square((2.0, 0.5), 0.2), range_max=GEOMETRY.range_max)
        seen = perception.from_scan(ranges, GEOMETRY, robot, 0.1 * k)
        assert not any(r.moving for _, r in seen.regions), (k, seen.regions)
