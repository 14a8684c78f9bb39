"""Tests of nmpc_avoid_ros.ros.markers: MarkerArray <-> core regions with RViz semantics."""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numpy as np
import pytest
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point, Quaternion
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from visualization_msgs.msg import Marker, MarkerArray

from nmpc_avoid_ros.core.errors import InputError, RegionError
from nmpc_avoid_ros.core.problem.regions import Ellipse, Polygon, SlotLayout, rotated_box
from nmpc_avoid_ros.ros.markers import (
    MESSAGE_ID,
    ApplyReport,
    RegionStore,
    delete_all_marker,
    delete_marker,
    ellipse_marker,
    quaternion_to_yaw,
    region_marker,
    regions_to_markers,
    yaw_to_quaternion,
)

SAMPLE_POINTS = [(x, y) for x in np.linspace(-4, 4, 9) for y in np.linspace(-4, 4, 9)]


def marker(
    type_: int = Marker.CYLINDER,
    ns: str = "obs",
    id_: int = 0,
    action: int = Marker.ADD,
    frame: str = "state",
    pos: tuple[float, float] = (0.0, 0.0),
    scale: tuple[float, float] = (1.0, 1.0),
    yaw: float | None = 0.0,
    points: list[tuple[float, float]] | None = None,
    lifetime: float = 0.0,
) -> Marker:
    m = Marker()
    m.header.frame_id = frame
    m.ns, m.id, m.type, m.action = ns, id_, type_, action
    m.pose.position.x, m.pose.position.y = pos
    if yaw is not None:
        m.pose.orientation = yaw_to_quaternion(yaw)
    m.scale.x, m.scale.y, m.scale.z = scale[0], scale[1], 0.1
    if points is not None:
        m.points = [Point(x=float(px), y=float(py)) for px, py in points]
    sec = math.floor(lifetime)
    m.lifetime = Duration(sec=sec, nanosec=round((lifetime - sec) * 1e9))
    return m


def array(*markers: Marker) -> MarkerArray:
    return MarkerArray(markers=list(markers))


def assert_same_region(a, b) -> None:
    """Same kind, frame and depth everywhere on a grid (yaw may differ by 2 pi)."""
    assert type(a) is type(b)
    assert a.frame == b.frame
    for p in SAMPLE_POINTS:
        assert a.depth(p) == pytest.approx(b.depth(p), abs=1e-9)


# --- round trip and shapes ------------------------------------------------------------------------


def test_round_trip_regions_to_markers_to_store() -> None:
    regions = [
        Ellipse((1.0, -0.5), (1.5, 0.4), yaw=0.7),
        Ellipse((-2.0, 2.0), (0.3, 0.3), yaw=4.0, frame="output"),  # yaw > pi comes back wrapped
        rotated_box((0.5, 0.5), (2.0, 1.0), yaw=-0.3),
        Polygon(((0.0, 0.0), (1.0, 0.0), (0.5, 1.0)), frame="output"),
    ]
    store = RegionStore()
    report = store.apply(regions_to_markers(regions, stamp=12.5), now=0.0)
    assert report == ApplyReport(applied=4, deleted=0, rejected=[], changed=True, keys_changed=True)
    active = store.active(now=1.0)
    # sorted by (ns, id) = the order given
    assert len(active) == 4
    for a, b in zip(regions, active, strict=True):
        assert_same_region(a, b)
    assert active[0] == regions[0]
    assert active[1].yaw == pytest.approx(4.0 - 2 * math.pi)
    assert active[3].vertices == regions[3].vertices


def test_regions_to_markers_shapes() -> None:
    msg = regions_to_markers([Ellipse((1.0, 2.0), (0.5, 0.25)), rotated_box((0, 0), (1, 1))], stamp=3.25, ns="demo")
    clear, cyl, strip = msg.markers
    assert clear.action == Marker.DELETEALL
    assert (cyl.type, cyl.ns, cyl.id, cyl.header.frame_id) == (Marker.CYLINDER, "demo", 0, "state")
    assert (cyl.scale.x, cyl.scale.y, cyl.scale.z) == (1.0, 0.5, 0.01)
    assert (cyl.header.stamp.sec, cyl.header.stamp.nanosec) == (3, 250_000_000)
    assert cyl.color.a > 0  # alpha 0 would be invisible in RViz
    assert strip.type == Marker.LINE_STRIP and strip.id == 1
    assert len(strip.points) == 5 and strip.points[0] == strip.points[-1]  # closed
    assert strip.scale.x > 0
    assert len(regions_to_markers([], replace=False).markers) == 0


def test_regions_to_markers_replace_drops_regions_no_longer_listed() -> None:
    store = RegionStore()
    store.apply(regions_to_markers([Ellipse((0, 0), (1, 1)), Ellipse((3, 0), (1, 1))]), now=0.0)
    report = store.apply(regions_to_markers([Ellipse((5, 5), (1, 1))]), now=1.0)
    assert (report.deleted, report.applied, report.changed) == (2, 1, True)
    assert store.active(1.0) == (Ellipse((5, 5), (1, 1)),)


def test_sphere_and_cylinder_are_ellipses_with_half_scales() -> None:
    store = RegionStore()
    store.apply(array(marker(Marker.SPHERE, id_=0, pos=(1, 2), scale=(3, 1)),
                      marker(Marker.CYLINDER, id_=1, pos=(-1, 0), scale=(0.5, 2))), now=0.0)
    assert store.active(0.0) == (Ellipse((1, 2), (1.5, 0.5)), Ellipse((-1, 0), (0.25, 1.0)))


def test_yaw_from_quaternion_rotates_the_ellipse() -> None:
    store = RegionStore()
    # 4 x 1 ellipse turned by 90 degrees: long axis along y
    store.apply(array(marker(Marker.CYLINDER, scale=(4.0, 1.0), yaw=math.pi / 2)), now=0.0)
    (ellipse,) = store.active(0.0)
    assert ellipse.yaw == pytest.approx(math.pi / 2)
    assert ellipse.depth((0.0, 1.5)) == pytest.approx(1 - (1.5 / 2.0) ** 2)  # inside along the long axis
    assert ellipse.depth((1.5, 0.0)) == pytest.approx(1 - (1.5 / 0.5) ** 2)  # far outside across it


def test_yaw_from_quaternion_rotates_the_cube() -> None:
    store = RegionStore()
    store.apply(array(marker(Marker.CUBE, scale=(2.0, 2.0), yaw=math.pi / 4)), now=0.0)
    (box,) = store.active(0.0)
    assert isinstance(box, Polygon)
    # a diamond: (1.3, 0) is inside (unrotated it would be outside), at distance 1 - 1.3/sqrt(2) from an edge
    assert box.depth((1.3, 0.0)) == pytest.approx(1 - 1.3 / math.sqrt(2))
    assert box.depth((0.9, 0.9)) < 0


def test_quaternion_conventions() -> None:
    assert quaternion_to_yaw(Quaternion(x=0.0, y=0.0, z=0.0, w=0.0)) == 0.0  # ros2 topic pub default
    assert quaternion_to_yaw(Quaternion(x=0.0, y=0.0, z=0.0, w=-1.0)) == pytest.approx(0.0)
    for yaw in np.linspace(-3.1, 3.1, 13):
        assert quaternion_to_yaw(yaw_to_quaternion(yaw)) == pytest.approx(yaw)
        q = yaw_to_quaternion(yaw)  # -q is the same rotation
        assert quaternion_to_yaw(Quaternion(x=0.0, y=0.0, z=-q.z, w=-q.w)) == pytest.approx(yaw)
    # slightly denormalised (within 1e-3) is accepted
    assert quaternion_to_yaw(Quaternion(x=0.0, y=0.0, z=0.0, w=1.0005)) == 0.0
    with pytest.raises(RegionError, match="unit quaternion"):
        quaternion_to_yaw(Quaternion(x=0.0, y=0.0, z=0.0, w=1.01))
    with pytest.raises(RegionError, match="about z"):
        quaternion_to_yaw(Quaternion(x=math.sin(0.2), y=0.0, z=0.0, w=math.cos(0.2)))
    with pytest.raises(RegionError, match="NaN"):
        quaternion_to_yaw(Quaternion(x=0.0, y=0.0, z=math.nan, w=1.0))


def test_all_zero_quaternion_marker_is_identity() -> None:
    m = marker(Marker.CUBE, scale=(2.0, 1.0), yaw=None)
    m.pose.orientation = Quaternion(x=0.0, y=0.0, z=0.0, w=0.0)
    store = RegionStore()
    assert store.apply(array(m), 0.0).applied == 1
    assert_same_region(store.active(0.0)[0], rotated_box((0, 0), (2, 1)))


def test_line_strip_open_closed_and_posed() -> None:
    tri = [(0.0, 0.0), (2.0, 0.0), (0.0, 2.0)]
    store = RegionStore()
    report = store.apply(array(
        marker(Marker.LINE_STRIP, id_=0, points=tri),
        marker(Marker.LINE_STRIP, id_=1, points=[*tri, tri[0]]),
        # RViz draws points in the pose frame: shifted by (10, 0) and turned by 90 degrees
        marker(Marker.LINE_STRIP, id_=2, points=tri, pos=(10.0, 0.0), yaw=math.pi / 2),
    ), now=0.0)
    assert report.applied == 3 and not report.rejected
    open_, closed, posed = store.active(0.0)
    assert open_.vertices == closed.vertices == tuple(tri)
    np.testing.assert_allclose(posed.vertices, [(10.0, 0.0), (10.0, 2.0), (8.0, 0.0)], atol=1e-12)


def test_frames() -> None:
    store = RegionStore()
    report = store.apply(array(marker(id_=0, frame=""), marker(id_=1, frame="output"),
                               marker(id_=2, frame="map"), marker(id_=3, frame="State")), now=0.0)
    assert [r.frame for r in store.active(0.0)] == ["state", "output"]
    assert [(ns, i) for ns, i, _ in report.rejected] == [("obs", 2), ("obs", 3)]
    assert all("frame_id" in reason for _, _, reason in report.rejected)

    out_default = RegionStore(default_frame="output")
    out_default.apply(array(marker(frame="")), now=0.0)
    assert out_default.active(0.0)[0].frame == "output"

    no_output = RegionStore(output_frame_available=False)
    report = no_output.apply(array(marker(frame="output")), now=0.0)
    assert len(report.rejected) == 1 and "output" in report.rejected[0][2]
    with pytest.raises(InputError):
        RegionStore(default_frame="map")


# --- actions ------------------------------------------------------------------------------------


def test_modify_replaces_and_delete_removes_by_key() -> None:
    store = RegionStore()
    store.apply(array(marker(ns="a", id_=1), marker(ns="b", id_=1), marker(ns="a", id_=2)), now=0.0)
    report = store.apply(array(marker(ns="a", id_=1, pos=(5.0, 5.0))), now=0.0)  # MODIFY == ADD
    assert Marker.MODIFY == Marker.ADD
    assert (report.applied, report.changed, report.keys_changed) == (1, True, False)  # moved, same set
    assert store.active(0.0)[0].center == (5.0, 5.0)
    report = store.apply(array(delete_marker("a", 1), delete_marker("a", 99)), now=0.0)
    assert (report.deleted, report.rejected, report.changed, report.keys_changed) == (1, [], True, True)
    assert [k for k, _ in store.active_items(0.0)] == [("a", 2), ("b", 1)]
    # replacing with another kind moves the key from ellipse to polygon
    store.apply(array(marker(Marker.CUBE, ns="a", id_=2)), now=0.0)
    assert isinstance(store.active(0.0)[0], Polygon)


def test_deleteall_clears_every_namespace_and_later_markers_apply() -> None:
    store = RegionStore()
    store.apply(array(marker(ns="a", id_=1), marker(ns="b", id_=7)), now=0.0)
    clear = delete_all_marker()
    clear.ns = "a"  # ROS 2: DELETEALL ignores ns
    report = store.apply(array(clear, marker(ns="c", id_=3)), now=0.0)
    assert (report.deleted, report.applied) == (2, 1)
    assert [k for k, _ in store.active_items(0.0)] == [("c", 3)]


@pytest.mark.parametrize("action", [1, 4, -1, 100])
def test_unknown_action_is_rejected(action: int) -> None:
    store = RegionStore()
    report = store.apply(array(marker(action=action, id_=4), marker(id_=5)), now=0.0)
    assert report.rejected == [("obs", 4, report.rejected[0][2])]
    assert f"unknown action {action}" in report.rejected[0][2]
    assert report.applied == 1


def test_reapplying_the_same_message_is_not_a_change() -> None:
    store = RegionStore()
    msg = regions_to_markers([Ellipse((0, 0), (1, 2))])
    assert store.apply(msg, 0.0).changed
    rev = store.revision
    report = store.apply(msg, 1.0)  # e.g. a transient-local re-delivery
    assert report.changed is False and store.revision == rev


def test_active_order_is_sorted_by_ns_then_id() -> None:
    store = RegionStore(max_ellipses=10)
    keys = [("b", 2), ("a", 10), ("b", -1), ("a", 2)]
    store.apply(array(*(marker(ns=ns, id_=i, pos=(float(i), 0.0)) for ns, i in keys)), now=0.0)
    assert [k for k, _ in store.active_items(0.0)] == sorted(keys)
    assert [r.center[0] for r in store.active(0.0)] == [2.0, 10.0, -1.0, 2.0]


# --- lifetime -----------------------------------------------------------------------------------


def test_lifetime_expiry_on_the_node_clock() -> None:
    store = RegionStore()
    store.apply(array(marker(id_=0, lifetime=2.0), marker(id_=1, lifetime=0.0), marker(id_=2, lifetime=0.5)), now=10.0)
    assert len(store.active(10.49)) == 3
    assert [k for k, _ in store.active_items(11.99)] == [("obs", 0), ("obs", 1)]
    rev = store.revision
    assert [k for k, _ in store.active_items(12.0)] == [("obs", 1)]
    assert store.revision > rev  # expiry is a change the controller must repack for
    assert len(store.active(1e9)) == 1  # lifetime 0 = forever


def test_readding_refreshes_the_lifetime() -> None:
    store = RegionStore()
    store.apply(array(marker(lifetime=1.0)), now=0.0)
    store.apply(array(marker(lifetime=1.0)), now=0.8)
    assert len(store.active(1.5)) == 1
    assert len(store.active(1.8)) == 0


def test_negative_lifetime_is_rejected() -> None:
    m = marker()
    m.lifetime = Duration(sec=-3, nanosec=0)
    report = RegionStore().apply(array(m), now=0.0)
    assert "lifetime" in report.rejected[0][2]


def test_now_must_be_finite() -> None:
    with pytest.raises(InputError):
        RegionStore().active(math.nan)


# --- capacity and rejection ---------------------------------------------------------------------


def test_capacity_per_kind() -> None:
    store = RegionStore(max_ellipses=2, max_polygons=1)
    report = store.apply(array(
        marker(id_=0), marker(id_=1), marker(id_=2),  # third ellipse too many
        marker(Marker.CUBE, id_=3), marker(Marker.CUBE, id_=4),  # second polygon too many
    ), now=0.0)
    assert report.applied == 3
    assert [(i, "capacity" in reason) for _, i, reason in report.rejected] == [(2, True), (4, True)]
    assert [k[1] for k, _ in store.active_items(0.0)] == [0, 1, 3]
    # at capacity, replacing an existing key of the same kind is fine
    assert store.apply(array(marker(id_=1, pos=(3.0, 3.0))), now=0.0).applied == 1
    # a region of the other kind cannot take an ellipse key when polygons are full
    report = store.apply(array(marker(Marker.CUBE, id_=1)), now=0.0)
    assert report.applied == 0 and "capacity" in report.rejected[0][2]
    assert store.active(0.0)[1].center == (3.0, 3.0)  # the old region stays
    # what the store holds always fits the NLP slots
    SlotLayout(max_ellipses=2, max_polygons=1).pack(store.active(0.0))


def test_expired_regions_free_capacity() -> None:
    store = RegionStore(max_ellipses=1)
    store.apply(array(marker(id_=0, lifetime=1.0)), now=0.0)
    assert store.apply(array(marker(id_=1)), now=0.5).rejected
    assert store.apply(array(marker(id_=1)), now=1.0).applied == 1


def test_polygon_vertex_capacity_and_from_layout() -> None:
    store = RegionStore.from_layout(SlotLayout(max_ellipses=1, max_polygons=2, max_polygon_vertices=4))
    square = [(0, 0), (1, 0), (1, 1), (0, 1)]
    pentagon = [(math.cos(a), math.sin(a)) for a in np.linspace(0, 2 * math.pi, 5, endpoint=False)]
    report = store.apply(array(marker(Marker.LINE_STRIP, id_=0, points=[*square, square[0]]),
                               marker(Marker.LINE_STRIP, id_=1, points=pentagon),
                               marker(Marker.LINE_STRIP, id_=2, points=square * 100)), now=0.0)
    assert report.applied == 1
    assert [i for _, i, _ in report.rejected] == [1, 2]
    assert all("capacity" in reason for _, _, reason in report.rejected)


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"scale": (math.nan, 1.0)}, "NaN"),
        ({"scale": (math.inf, 1.0)}, "NaN or infinite"),
        ({"scale": (-1.0, 1.0)}, "positive"),
        ({"scale": (0.0, 1.0)}, "positive"),
        ({"scale": (1e-12, 1.0)}, "positive"),
        ({"pos": (math.nan, 0.0)}, "position"),
        ({"pos": (1e7, 0.0)}, "within"),
        ({"type_": Marker.ARROW}, "unsupported marker type 0 (ARROW)"),
        ({"type_": Marker.TEXT_VIEW_FACING}, "TEXT_VIEW_FACING"),
        ({"type_": 42}, "unsupported marker type 42"),
        ({"type_": Marker.LINE_STRIP, "points": [(0, 0), (1, 0)]}, "at least 3"),
        ({"type_": Marker.LINE_STRIP, "points": [(0, 0), (1, 0), (2, 0)]}, "convex"),
        ({"type_": Marker.LINE_STRIP, "points": [(0, 0), (2, 0), (1, 0.2), (2, 2), (0, 2)]}, "convex"),
        ({"type_": Marker.LINE_STRIP, "points": [(0, 0), (1, math.inf), (0, 1)]}, "point"),
    ],
)
def test_invalid_marker_rejected_alone(kwargs: dict, fragment: str) -> None:
    store = RegionStore()
    store.apply(array(marker(id_=1, pos=(9.0, 9.0))), now=0.0)
    report = store.apply(array(marker(id_=0), marker(id_=1, **kwargs), marker(id_=2)), now=0.0)
    assert report.applied == 2
    assert len(report.rejected) == 1
    ns, i, reason = report.rejected[0]
    assert (ns, i) == ("obs", 1) and fragment in reason
    # the last good region under the rejected key stays in force
    assert [r.center for r in store.active(0.0)] == [(0.0, 0.0), (9.0, 9.0), (0.0, 0.0)]


def test_non_unit_or_tilted_quaternion_rejected() -> None:
    bad = marker(id_=3)
    bad.pose.orientation = Quaternion(x=0.0, y=0.0, z=0.5, w=0.5)
    tilted = marker(id_=4)
    tilted.pose.orientation = Quaternion(x=0.0, y=math.sin(0.1), z=0.0, w=math.cos(0.1))
    report = RegionStore().apply(array(bad, tilted), now=0.0)
    assert [i for _, i, _ in report.rejected] == [3, 4]


def test_oversized_message_rejected_as_a_whole_quickly() -> None:
    store = RegionStore(max_markers_per_message=1000)
    store.apply(array(marker(id_=0)), now=0.0)
    rev = store.revision
    flood = MarkerArray()
    flood.markers = [delete_all_marker()] * 1_000_001  # one object repeated: cheap to build
    start = time.perf_counter()
    report = store.apply(flood, now=0.0)
    assert time.perf_counter() - start < 0.05  # O(1): no per-marker work
    assert report.applied == report.deleted == 0 and not report.changed
    assert report.rejected[0][:2] == ("", MESSAGE_ID) and "1000001 markers" in report.rejected[0][2]
    assert store.revision == rev and len(store.active(0.0)) == 1


def test_garbage_objects_never_raise() -> None:
    store = RegionStore()

    fake = SimpleNamespace(markers=[None, 3, object(), marker(id_=9)])
    report = store.apply(fake, now=0.0)  # type: ignore[arg-type]
    assert report.applied == 1 and len(report.rejected) == 3
    assert all(reason for _, _, reason in report.rejected)
    # the catch-all names them as malformed objects, and only them
    assert report.malformed == [(ns, i) for ns, i, _ in report.rejected]
    assert store.apply(None, now=0.0).rejected  # type: ignore[arg-type]


def test_region_marker_helpers() -> None:
    e = Ellipse((1.0, 1.0), (0.5, 0.5), frame="output")
    m = ellipse_marker(e, marker_id=7, ns="demo", lifetime=1.5)
    assert (m.type, m.id, m.ns, m.header.frame_id) == (Marker.CYLINDER, 7, "demo", "output")
    assert (m.lifetime.sec, m.lifetime.nanosec) == (1, 500_000_000)
    assert region_marker(rotated_box((0, 0), (1, 1))).type == Marker.LINE_STRIP
    with pytest.raises(RegionError):
        region_marker("circle")  # type: ignore[arg-type]


# --- property-based -----------------------------------------------------------------------------

nasty_float = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([0.0, -0.0, 1e-12, -1.0, 0.5, 1.0, 2.0, 1e6, 2e6, math.nan, math.inf, -math.inf]),
    st.floats(min_value=-5, max_value=5),
)
quaternions = st.one_of(
    st.just((0.0, 0.0, 0.0, 0.0)),
    st.floats(-7, 7).map(lambda yaw: (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))),
)


def _mostly(draw: st.DrawFn, good: st.SearchStrategy, bad: st.SearchStrategy):
    """Each field is valid 80% of the time, so whole messages mix accepted and rejected markers."""
    return draw(good) if draw(st.integers(0, 9)) < 8 else draw(bad)


def _regular_polygon(n: int, radius: float, rotation: float) -> list[tuple[float, float]]:
    angles = [rotation + 2 * math.pi * k / n for k in range(n)]
    return [(radius * math.cos(a), radius * math.sin(a)) for a in angles]


@st.composite
def garbage_markers(draw: st.DrawFn) -> Marker:
    m = Marker()
    m.header.frame_id = _mostly(draw, st.sampled_from(["", "state", "output"]),
                                st.sampled_from(["map", "/state", "STATE", " state"]))
    m.ns = draw(st.sampled_from(["", "a", "b"]))
    m.id = draw(st.integers(-2, 4))
    m.type = _mostly(draw, st.sampled_from([1, 2, 3, 4]), st.integers(-3, 14))
    m.action = _mostly(draw, st.sampled_from([0, 0, 0, 0, 2, 3]), st.integers(-2, 5))
    m.pose.position.x, m.pose.position.y = _mostly(draw, st.tuples(st.floats(-5, 5), st.floats(-5, 5)),
                                                   st.tuples(nasty_float, nasty_float))
    qx, qy, qz, qw = _mostly(draw, quaternions, st.tuples(nasty_float, nasty_float, nasty_float, nasty_float))
    m.pose.orientation = Quaternion(x=qx, y=qy, z=qz, w=qw)
    m.scale.x, m.scale.y = _mostly(draw, st.tuples(st.floats(0.1, 3), st.floats(0.1, 3)),
                                   st.tuples(nasty_float, nasty_float))
    convex = st.builds(_regular_polygon, st.integers(3, 7), st.floats(0.1, 3), st.floats(-4, 4))
    points = _mostly(draw, convex, st.lists(st.tuples(nasty_float, nasty_float), max_size=12))
    m.points = [Point(x=x, y=y) for x, y in points]
    m.lifetime = _mostly(draw, st.builds(Duration, sec=st.integers(0, 2), nanosec=st.integers(0, 999_999_999)),
                         st.builds(Duration, sec=st.integers(-2, -1), nanosec=st.integers(0, 999_999_999)))
    return m


@pytest.mark.slow
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.lists(garbage_markers(), max_size=12), min_size=1, max_size=4))
def test_garbage_markers_never_raise_and_keep_the_store_valid(messages: list[list[Marker]]) -> None:
    layout = SlotLayout(max_ellipses=3, max_polygons=2, max_polygon_vertices=5)
    store = RegionStore.from_layout(layout)
    for step, markers in enumerate(messages):
        now = 0.7 * step
        report = store.apply(array(*markers), now=now)
        n_delete = sum(1 for m in markers if m.action in (Marker.DELETE, Marker.DELETEALL))
        # every marker is accounted for: applied, a delete action, or rejected with a reason
        assert report.applied + n_delete + len(report.rejected) == len(markers)
        keys = {(m.ns, m.id) for m in markers}
        for ns, i, reason in report.rejected:
            assert (ns, i) in keys
            assert isinstance(reason, str) and reason.strip()
        # rejected markers are exactly those of a rejected action, bad content or no capacity
        for m in markers:
            if m.action == Marker.ADD and not _converts(store, m):
                assert (m.ns, m.id) in {(ns, i) for ns, i, _ in report.rejected}
        active = store.active(now)
        for region in active:
            assert isinstance(region, (Ellipse, Polygon))
            rebuilt = Ellipse(region.center, region.semi_axes, region.yaw, region.frame) if isinstance(
                region, Ellipse) else Polygon(region.vertices, region.frame)
            assert rebuilt == region
        layout.pack(active)  # fits the NLP slots


def _converts(store: RegionStore, m: Marker) -> bool:
    try:
        store.marker_to_region(m)
        return m.lifetime.sec >= 0
    except (RegionError, InputError):
        return False


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.builds(lambda cx, cy, a, b, yaw, fr: Ellipse((cx, cy), (a, b), yaw, fr),
                      st.floats(-100, 100), st.floats(-100, 100), st.floats(0.01, 50), st.floats(0.01, 50),
                      st.floats(-10, 10), st.sampled_from(["state", "output"])),
            st.builds(lambda cx, cy, sx, sy, yaw: rotated_box((cx, cy), (sx, sy), yaw),
                      st.floats(-100, 100), st.floats(-100, 100), st.floats(0.01, 50), st.floats(0.01, 50),
                      st.floats(-10, 10)),
        ),
        max_size=6,
    ),
    st.floats(0, 1e6),
)
def test_round_trip_property(regions: list, stamp: float) -> None:
    store = RegionStore(max_ellipses=6, max_polygons=6)
    report = store.apply(regions_to_markers(regions, stamp=stamp), now=stamp)
    assert report.rejected == [] and report.applied == len(regions)
    active = store.active(stamp)
    assert len(active) == len(regions)
    for a, b in zip(regions, active, strict=True):
        assert type(a) is type(b) and a.frame == b.frame
        if isinstance(a, Ellipse):
            assert b.center == a.center and b.semi_axes == pytest.approx(a.semi_axes)
            assert math.cos(b.yaw - a.yaw) == pytest.approx(1.0)
        else:
            np.testing.assert_allclose(b.vertices, a.vertices, rtol=1e-12, atol=1e-9)
