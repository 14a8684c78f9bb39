"""Hostile input, fuzzed (issue 6, part 1): every converter of outside data raises only its
documented error (the NmpcError family) with a non-empty message, and whatever it accepts is
valid and finite.

Covered: state/target/command vectors (core.controller.validate_vector, ros.conversions with
Float64MultiArray of any layout), obstacle markers applied to ros.markers.RegionStore (random types,
actions, NaN/inf/huge numbers, non-unit quaternions, self-intersecting or oversized LINE_STRIPs,
lifetimes, frames), region parameters (Ellipse, Polygon, rotated_box, SlotLayout.pack), and YAML
configuration (load_params_file on random, broken and mutated files; ControllerSettings.from_params
on random mappings).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from builtin_interfaces.msg import Duration
from fuzzing import any_float, finite, fuzz_settings, garbage, huge_int, is_exc, outcome, scalar, time_limit
from geometry_msgs.msg import Point, Quaternion
from hypothesis import given
from hypothesis import strategies as st
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from visualization_msgs.msg import Marker, MarkerArray

from nmpc_avoid_ros.core.config.settings import ControllerSettings, default_config_path, load_params_file
from nmpc_avoid_ros.core.errors import ConfigError, InputError, RegionError
from nmpc_avoid_ros.core.problem.regions import Ellipse, Polygon, SlotLayout, rotated_box
from nmpc_avoid_ros.core.sample.step_result import validate_vector
from nmpc_avoid_ros.ros.conversions import array_to_vector, vector_to_array
from nmpc_avoid_ros.ros.markers import RegionStore

# --- vectors --------------------------------------------------------------------------------------

vector_like = st.one_of(
    st.lists(any_float, max_size=6),
    st.lists(st.floats(-1e9, 1e9), min_size=2, max_size=2),
    st.lists(st.integers(-(10**400), 10**400), max_size=3),
    garbage,
)


@fuzz_settings(200)
@given(vector_like, st.integers(0, 4))
def test_validate_vector_returns_a_finite_copy_or_input_error(values, size: int) -> None:
    """Accepted: exactly `size` finite numbers within +-1e12 (a target of 1e300 would overflow the NLP)."""
    got = outcome(lambda: validate_vector("state", values, size), (InputError,))
    if is_exc(got):
        assert str(got).startswith("state:")
        return
    assert got.dtype == float and got.shape == (size,) and np.all(np.isfinite(got)) and np.all(np.abs(got) <= 1e12)
    assert not isinstance(values, (str, bytes))
    np.testing.assert_array_equal(got, np.asarray(values, float).ravel())


layouts = st.builds(
    lambda dims, offset: (dims, offset),
    st.lists(st.builds(MultiArrayDimension, label=st.text(max_size=20), size=st.integers(0, 2**32 - 1),
                       stride=st.integers(0, 2**32 - 1)), max_size=4),
    st.integers(0, 2**32 - 1),
)


@fuzz_settings(150)
@given(st.one_of(st.lists(any_float, max_size=8), st.lists(st.floats(-2e12, 2e12), min_size=1, max_size=4)), layouts,
       st.integers(1, 4))
def test_array_to_vector_ignores_the_layout_and_rejects_bad_data(data, layout, size: int) -> None:
    msg = Float64MultiArray(data=data)
    msg.layout.dim, msg.layout.data_offset = layout
    got = outcome(lambda: array_to_vector(msg, size, "target"), (InputError,))
    ok = len(data) == size and finite(*data) and all(abs(v) <= 1e12 for v in data)
    assert is_exc(got) != ok, got
    if ok:
        assert got.tolist() == data  # exactly the data, whatever the layout says
        msg.data[0] = 123.0  # a copy: a reused message buffer does not change the accepted vector
        assert got[0] == data[0]
    else:
        assert "target" in str(got)


@fuzz_settings(150)
@given(st.one_of(st.lists(any_float, max_size=8), garbage), st.one_of(st.none(), st.text(max_size=10)))
def test_vector_to_array_round_trips_or_raises_input_error(values, label) -> None:
    msg = outcome(lambda: vector_to_array(values, label), (InputError,))
    if is_exc(msg):
        return
    arr = np.asarray(values, float).ravel()
    np.testing.assert_array_equal(np.asarray(msg.data), arr)
    assert [(d.label, d.size, d.stride) for d in msg.layout.dim] == [(label or "", arr.size, arr.size)]


# --- region parameters ----------------------------------------------------------------------------

number = st.one_of(st.floats(-10, 10), any_float, st.sampled_from([0.0, -0.0, 1e-12, 1e6, 2e6, 1e300]))
pair = st.one_of(st.tuples(number, number), st.lists(number, max_size=3), scalar, garbage)
frame = st.one_of(st.sampled_from(["state", "output"]), st.text(max_size=6), scalar)


def assert_simple_convex(poly: Polygon) -> None:
    """Every vertex on or inside every edge's half-plane and the outline turning exactly once."""
    planes = poly.half_planes()
    pts = np.asarray(poly.vertices)
    scale = 1.0 + np.max(np.abs(pts))
    assert np.all(pts @ planes[:, :2].T <= planes[:, 2] + 1e-7 * scale), "a vertex lies outside an edge"
    assert np.all(np.isfinite(planes)) and np.allclose(np.hypot(planes[:, 0], planes[:, 1]), 1.0)
    assert poly.depth(pts.mean(axis=0)) > 0  # the centroid is inside


@fuzz_settings(150)
@given(pair, pair, st.one_of(number, scalar), frame)
def test_ellipse_accepts_only_finite_positive_shapes(center, axes, yaw, fr) -> None:
    e = outcome(lambda: Ellipse(center, axes, yaw, fr), (RegionError,))
    if is_exc(e):
        return
    assert len(e.center) == len(e.semi_axes) == 2 and min(e.semi_axes) > 0 and e.frame in ("state", "output")
    assert np.all(np.isfinite(e.slot_values()))
    assert e.depth(e.center) == pytest.approx(1.0)


@fuzz_settings(150)
@given(pair, pair, st.one_of(number, scalar), frame)
def test_rotated_box_is_a_four_vertex_rectangle_or_region_error(center, size, yaw, fr) -> None:
    box = outcome(lambda: rotated_box(center, size, yaw, fr), (RegionError,))
    if is_exc(box):
        return
    assert len(box.vertices) == 4
    assert_simple_convex(box)
    pts = np.asarray(box.vertices)
    sx, sy = np.hypot(*(pts[1] - pts[0])), np.hypot(*(pts[2] - pts[1]))
    assert (sx, sy) == pytest.approx(tuple(float(v) for v in size), rel=1e-6, abs=1e-6)


def _star(n: int, step: int, radius: float) -> list[tuple[float, float]]:
    return [(radius * math.cos(2 * math.pi * k * step / n), radius * math.sin(2 * math.pi * k * step / n))
            for k in range(n)]


vertex_lists = st.one_of(
    st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), max_size=10),
    st.lists(st.tuples(number, number), max_size=6),
    st.builds(_star, st.sampled_from([5, 7, 8]), st.sampled_from([2, 3]), st.floats(0.1, 10)),  # self-intersecting
    st.builds(lambda n, r: _star(n, 1, r) * 2, st.integers(3, 6), st.floats(0.1, 10)),  # wound twice
    st.builds(_star, st.integers(3, 9), st.just(1), st.floats(1e-6, 1e5)),  # valid
    garbage,
)


@fuzz_settings(200)
@given(vertex_lists, frame)
def test_polygon_accepts_only_simple_convex_outlines(vertices, fr) -> None:
    poly = outcome(lambda: Polygon(vertices, fr), (RegionError,))
    if is_exc(poly):
        return
    assert_simple_convex(poly)
    assert np.all(np.isfinite(poly.slot_values(len(poly.vertices))))


def test_self_intersecting_star_is_refused() -> None:
    with pytest.raises(RegionError, match="simple"):
        Polygon(tuple(_star(5, 2, 1.0)))
    with pytest.raises(RegionError, match="simple"):
        Polygon(tuple(_star(4, 1, 1.0) * 2))


regions = st.lists(st.one_of(
    st.builds(Ellipse, st.tuples(st.floats(-5, 5), st.floats(-5, 5)), st.tuples(st.floats(0.1, 3), st.floats(0.1, 3)),
              st.floats(-4, 4), st.sampled_from(["state", "output"])),
    st.builds(rotated_box, st.tuples(st.floats(-5, 5), st.floats(-5, 5)),
              st.tuples(st.floats(0.1, 3), st.floats(0.1, 3)), st.floats(-4, 4)),
    st.builds(lambda n, r: Polygon(tuple(_star(n, 1, r))), st.integers(3, 9), st.floats(0.1, 3)),
    scalar,
), max_size=8)


@fuzz_settings(150)
@given(regions, st.one_of(st.integers(-1, 4), scalar), st.one_of(st.integers(-1, 3), scalar),
       st.one_of(st.integers(2, 9), scalar), st.booleans())
def test_slot_layout_pack_is_finite_and_sized_or_region_error(items, n_ell, n_poly, n_vert, output_ok) -> None:
    layout = outcome(lambda: SlotLayout(n_ell, n_poly, n_vert), (RegionError,))
    if is_exc(layout):
        return
    values = outcome(lambda: layout.pack(items, output_ok), (RegionError,))
    if is_exc(values):
        return
    assert values.shape == (layout.size,) and np.all(np.isfinite(values))
    active_flags = values[: 8 * layout.max_ellipses : 8]  # slot value 0 of each ellipse slot
    assert int(active_flags.sum()) == sum(isinstance(r, Ellipse) for r in items)


# --- markers --------------------------------------------------------------------------------------

marker_float = st.one_of(st.floats(-5, 5), any_float, st.sampled_from([0.0, -0.0, 1e-300, 1e300, 2e6, -1.0]))


@st.composite
def hostile_markers(draw: st.DrawFn) -> Marker:
    """Any field may be garbage; with half a chance a field is sensible so markers also get accepted."""
    sensible = draw(st.booleans())
    m = Marker()
    m.header.frame_id = draw(st.sampled_from(["", "state", "output"]) if sensible else
                             st.one_of(st.sampled_from(["map", "State", "state "]), st.text(max_size=30)))
    m.ns = draw(st.one_of(st.sampled_from(["", "a"]), st.text(max_size=12)))
    m.id = draw(st.one_of(st.integers(0, 3), st.integers(-(2**31), 2**31 - 1)))
    m.type = draw(st.sampled_from([1, 2, 3, 4]) if sensible else st.integers(-(2**31), 2**31 - 1))
    m.action = draw(st.sampled_from([0, 0, 2, 3]) if sensible else st.integers(-(2**31), 2**31 - 1))
    m.pose.position.x, m.pose.position.y, m.pose.position.z = draw(st.tuples(marker_float, marker_float, any_float))
    yaw_quat = st.floats(-7, 7).map(lambda y: (0.0, 0.0, math.sin(y / 2), math.cos(y / 2)))
    qx, qy, qz, qw = draw(yaw_quat if sensible else st.tuples(marker_float, marker_float, marker_float, marker_float))
    m.pose.orientation = Quaternion(x=qx, y=qy, z=qz, w=qw)
    m.scale.x, m.scale.y, m.scale.z = draw(st.tuples(st.floats(0.05, 3) if sensible else marker_float,
                                                     st.floats(0.05, 3) if sensible else marker_float, any_float))
    points = draw(st.one_of(
        st.builds(_star, st.integers(3, 12), st.just(1), st.floats(0.1, 3)),
        st.builds(_star, st.sampled_from([5, 7]), st.just(2), st.floats(0.1, 3)),  # self-intersecting
        st.lists(st.tuples(marker_float, marker_float), max_size=14),
        st.lists(st.tuples(st.floats(-1, 1), st.floats(-1, 1)), max_size=4),  # mostly degenerate/non-convex
    ))
    m.points = [Point(x=x, y=y, z=0.0) for x, y in points]
    m.lifetime = Duration(sec=draw(st.one_of(st.integers(0, 3), st.integers(-(2**31), 2**31 - 1))),
                          nanosec=draw(st.integers(0, 2**32 - 1)))
    return m


def check_store(store: RegionStore, now: float) -> None:
    """What the store holds is valid and always fits the NLP's slots."""
    active = store.active(now)
    for region in active:
        if isinstance(region, Polygon):
            assert 3 <= len(region.vertices) <= store.max_polygon_vertices
            assert_simple_convex(region)
        else:
            assert min(region.semi_axes) > 0 and finite(*region.center, *region.semi_axes, region.yaw)
    layout = SlotLayout(store.max_ellipses, store.max_polygons, store.max_polygon_vertices)
    assert np.all(np.isfinite(layout.pack(list(active))))


@fuzz_settings(50)
@given(st.lists(st.lists(hostile_markers(), max_size=8), min_size=1, max_size=3),
       st.floats(0, 1e6), st.floats(0, 5))
def test_region_store_never_raises_and_holds_only_valid_regions(messages, t0: float, dt: float) -> None:
    store = RegionStore(max_ellipses=3, max_polygons=2, max_polygon_vertices=6)
    for k, markers in enumerate(messages):
        now = t0 + k * dt
        report = store.apply(MarkerArray(markers=markers), now)
        for _ns, _id, reason in report.rejected:
            assert reason.strip()
        # the store's catch-all for malformed objects must never be what handles a real Marker
        assert report.malformed == [], report.rejected
        check_store(store, now)


@fuzz_settings(100)
@given(hostile_markers(), st.floats(0, 100))
def test_a_rejected_marker_leaves_the_store_as_it_was(marker: Marker, now: float) -> None:
    store = RegionStore(max_ellipses=3, max_polygons=2, max_polygon_vertices=6)
    good = Marker(type=Marker.CYLINDER, ns=marker.ns, id=marker.id)
    good.header.frame_id = "state"
    good.scale.x = good.scale.y = 1.0
    assert store.apply(MarkerArray(markers=[good]), now).applied == 1
    before = store.active(now)
    report = store.apply(MarkerArray(markers=[marker]), now)
    if report.rejected:
        assert store.active(now) == before  # the last good region under that key stays in force
    check_store(store, now)


# --- YAML configuration ---------------------------------------------------------------------------

FIELDS = [f.name for f in dataclasses.fields(ControllerSettings)]
param_value = st.one_of(scalar, st.lists(scalar, max_size=4), st.lists(st.floats(-10, 10), max_size=3),
                        st.lists(st.integers(-3, 3), max_size=3), garbage)


def assert_valid_settings(s: ControllerSettings) -> None:
    s.validate()
    for f in dataclasses.fields(s):
        value = getattr(s, f.name)
        if isinstance(value, float):
            assert math.isfinite(value), f.name
    for name in ("state_min", "state_max", "input_min", "input_max", "state_weights", "input_weights"):
        assert all(finite(float(v)) for v in getattr(s, name)), name


@fuzz_settings(200)
@given(st.dictionaries(st.one_of(st.sampled_from(FIELDS), st.text(max_size=8), st.integers()), param_value,
                       max_size=5))
def test_from_params_on_random_mappings_raises_only_config_error(params) -> None:
    s = outcome(lambda: ControllerSettings.from_params(params), (ConfigError,))
    if not is_exc(s):
        assert_valid_settings(s)


@fuzz_settings(50)
@given(st.one_of(scalar, st.lists(scalar, max_size=3)))
def test_from_params_refuses_a_non_mapping(params) -> None:
    assert is_exc(outcome(lambda: ControllerSettings.from_params(params), (ConfigError,)))


SHIPPED = default_config_path().read_bytes()


def _load(path: Path) -> None:
    with time_limit(5.0):
        pf = outcome(lambda: load_params_file(path), (ConfigError,))
        if is_exc(pf):
            return
        for name in pf.nodes:
            assert isinstance(pf.section(name), dict)
        s = outcome(lambda: ControllerSettings.from_params(pf.section("controller")), (ConfigError,))
        if not is_exc(s):
            assert_valid_settings(s)


yaml_documents = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=10), huge_int),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=20,
)


@fuzz_settings(100)
@given(st.one_of(
    st.binary(max_size=300),
    st.text(max_size=300).map(str.encode),
    yaml_documents.map(lambda d: yaml.safe_dump(d).encode()),
    st.dictionaries(st.sampled_from(FIELDS), yaml_documents, max_size=4).map(
        lambda p: yaml.safe_dump({"controller": {"ros__parameters": p}}, allow_unicode=True).encode()),
    st.sampled_from([b"\xff\xfe\x00", b"&a [*a]", b"controller: &x {ros__parameters: *x}",
                     b"controller: {ros__parameters: &p {model: van_der_pol, keep_in: *p}}"]),
))
def test_load_params_file_on_random_files_raises_only_config_error(tmp_path_factory, data: bytes) -> None:
    path = tmp_path_factory.mktemp("yaml") / "params.yaml"
    path.write_bytes(data)
    _load(path)


@fuzz_settings(150)
@given(st.data())
def test_mutated_shipped_config_raises_only_config_error(tmp_path_factory, data) -> None:
    raw = bytearray(SHIPPED)
    how = data.draw(st.sampled_from(["truncate", "flip", "overwrite", "delete"]))
    i = data.draw(st.integers(0, len(raw) - 1))
    if how == "truncate":
        raw = raw[:i]
    elif how == "flip":
        raw[i] ^= 1 << data.draw(st.integers(0, 7))
    elif how == "overwrite":
        raw[i] = data.draw(st.sampled_from(b":-[]{}&*!|>#'\"\t\n 0.eE"))
    else:
        del raw[i:i + data.draw(st.integers(1, 40))]
    path = tmp_path_factory.mktemp("yaml") / "mutated.yaml"
    path.write_bytes(bytes(raw))
    _load(path)


def test_unreadable_params_files_are_config_errors(tmp_path: Path) -> None:
    (tmp_path / "latin1.yaml").write_bytes(b"controller:\n  ros__parameters: {model: \xe9}\n")
    (tmp_path / "deep.yaml").write_bytes(b"[" * 1_000)  # RecursionError inside the YAML parser
    (tmp_path / "indent.yaml").write_bytes(b"a:\n" + b"".join(b" " * i + b"b:\n" for i in range(1, 600)))
    paths = ["latin1.yaml", "deep.yaml", "indent.yaml", ".", "missing.yaml"]
    for path in [tmp_path / p for p in paths] + ["a\0b"]:
        with pytest.raises(ConfigError) as info:
            load_params_file(path)
        assert str(info.value)
