"""Penalty of every region type: zero outside, positive inside, the paper's sign convention."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from nmpc_avoid_ros.core.errors import RegionError
from nmpc_avoid_ros.core.problem.expressions import parse_keep_in
from nmpc_avoid_ros.core.problem.models import make_model
from nmpc_avoid_ros.core.problem.regions import Ellipse, Polygon, SlotLayout, rotated_box

LAYOUT = SlotLayout(max_ellipses=2, max_polygons=2, max_polygon_vertices=6)


def penalty_function(layout: SlotLayout = LAYOUT) -> ca.Function:
    """F(point, slots) = sum max(0, active g)^2 over the slots, as the NLP builds it."""
    point = ca.SX.sym("p", 2)
    slots = ca.SX.sym("s", layout.size)
    F = ca.sumsqr(ca.fmax(0, layout.depths(slots, point, None)))
    return ca.Function("F", [point, slots], [F])


def F(regions, point) -> float:
    return float(penalty_function()(point, LAYOUT.pack(regions)))


REGIONS = {
    "ellipse": Ellipse((1.0, 2.0), (2.0, 0.5), yaw=0.3),
    "box": rotated_box((-1.0, 0.0), (2.0, 1.0), yaw=math.pi / 6),
    "triangle": Polygon(((0.0, 0.0), (3.0, 0.0), (0.0, 3.0))),
    "clockwise": Polygon(((0.0, 0.0), (0.0, 3.0), (3.0, 0.0))),
}
CENTRES = {"ellipse": (1.0, 2.0), "box": (-1.0, 0.0), "triangle": (0.8, 0.8), "clockwise": (0.8, 0.8)}


@pytest.mark.parametrize("name", REGIONS)
def test_penalty_positive_inside_zero_outside(name):
    region = REGIONS[name]
    assert F([region], CENTRES[name]) > 0
    assert region.depth(CENTRES[name]) > 0
    assert F([region], (10.0, 10.0)) == 0.0
    assert region.depth((10.0, 10.0)) < 0


@pytest.mark.parametrize("name", REGIONS)
def test_numeric_depth_matches_the_symbolic_penalty(name):
    region = REGIONS[name]
    rng = np.random.default_rng(0)
    for point in rng.uniform(-4, 4, size=(50, 2)):
        assert F([region], point) == pytest.approx(max(0.0, region.depth(point)) ** 2, abs=1e-12)


def test_ellipse_yaw_rotates_the_long_axis():
    e = Ellipse((0.0, 0.0), (2.0, 0.5), yaw=math.pi / 2)
    assert e.depth((0.0, 1.5)) > 0  # along the rotated long axis
    assert e.depth((1.5, 0.0)) < 0


def test_box_corners_and_polygon_depth_is_distance_to_nearest_edge():
    box = rotated_box((0.0, 0.0), (4.0, 2.0))
    assert box.depth((0.0, 0.0)) == pytest.approx(1.0)
    assert box.depth((1.5, 0.0)) == pytest.approx(0.5)
    assert box.depth((2.5, 0.0)) == pytest.approx(-0.5)


def test_inactive_slots_add_nothing():
    assert float(penalty_function()((0.0, 0.0), np.zeros(LAYOUT.size))) == 0.0


def test_paper_region_sign_convention():
    """g1 = x1 x2 - 2, g2 = -x1 x2 - 2: F is zero exactly where |x1 x2| <= 2."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    symbols = make_model("van_der_pol").symbol_table(x, u)
    gs = [parse_keep_in(t, symbols).g for t in ("x1*x2 - 2 <= 0", "-x1*x2 - 2 <= 0")]
    Ff = ca.Function("F", [x, u], [ca.sumsqr(ca.fmax(0, ca.vertcat(*gs)))])
    assert float(Ff([1.0, 1.9], 0)) == 0.0
    assert float(Ff([-3.0, 0.6], 0)) == 0.0
    assert float(Ff([3.0, 1.0], 0)) == pytest.approx(1.0)
    assert float(Ff([-3.0, 1.0], 0)) == pytest.approx(1.0)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: Ellipse((0, 0), (-1, 1)), "positive"),
        (lambda: Ellipse((math.nan, 0), (1, 1)), "finite"),
        (lambda: Ellipse((0, 0), (1, 1), frame="map"), "frame"),
        (lambda: Polygon(((0, 0), (1, 0))), "at least 3"),
        (lambda: Polygon(((0, 0), (2, 0), (1, 0.2), (2, 2), (0, 2))), "convex"),
        (lambda: Polygon(((0, 0), (1, 1), (2, 2))), "convex"),
        (lambda: rotated_box((0, 0), (0, 1)), "positive"),
        (lambda: Polygon(((0, 0), (1, "a"), (2, 2))), "numbers"),
    ],
)
def test_malformed_regions_get_clear_errors(make, message):
    with pytest.raises(RegionError, match=message):
        make()


def test_capacity_and_frame_checks_of_the_slot_layout():
    with pytest.raises(RegionError, match="capacity"):
        LAYOUT.pack([Ellipse((i, 0), (1, 1)) for i in range(3)])
    with pytest.raises(RegionError, match="fewer than 2"):
        LAYOUT.pack([Ellipse((0, 0), (1, 1), frame="output")], output_frame_available=False)
    big = Polygon(tuple((math.cos(a), math.sin(a)) for a in np.linspace(0, 2 * math.pi, 8, endpoint=False)))
    with pytest.raises(RegionError, match="capacity"):
        LAYOUT.pack([big])


coords = st.floats(-5, 5, allow_nan=False)


@given(cx=coords, cy=coords, a=st.floats(0.05, 3), b=st.floats(0.05, 3), yaw=st.floats(-4, 4), px=coords, py=coords)
def test_ellipse_depth_sign_matches_the_rotated_quadratic_form(cx, cy, a, b, yaw, px, py):
    e = Ellipse((cx, cy), (a, b), yaw)
    c, s = math.cos(yaw), math.sin(yaw)
    ex = c * (px - cx) + s * (py - cy)
    ey = -s * (px - cx) + c * (py - cy)
    r2 = (ex / a) ** 2 + (ey / b) ** 2
    assert e.depth((px, py)) == pytest.approx(1 - r2, rel=1e-9, abs=1e-9)


# --- the clearance margin (region_margin): inflated regions ---------------------------------------
@given(st.floats(0.2, 3.0), st.floats(0.05, 3.0), st.floats(-3.2, 3.2), st.floats(0.01, 1.0),
       st.floats(-math.pi, math.pi), st.floats(0.0, 0.999))
def test_an_inflated_ellipse_holds_the_points_near_the_ellipse(a, b, yaw, margin, angle, fraction):
    ellipse = Ellipse((1.0, -2.0), (a, b), yaw)
    grown = ellipse.inflated(margin)
    assert grown.semi_axes == pytest.approx((a + margin, b + margin))
    # a boundary point of the ellipse pushed out along its outward normal by `distance`
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([a * math.cos(angle), b * math.sin(angle)])
    normal = np.array([math.cos(angle) / a, math.sin(angle) / b])
    rotate = np.array([[c, -s], [s, c]])
    point, normal = rotate @ local + (1.0, -2.0), rotate @ (normal / np.linalg.norm(normal))
    guaranteed = margin * min(a, b) / max(a, b)  # Ellipse.inflated: (b / a) margin in any direction
    assert grown.depth(point + fraction * guaranteed * normal) > -1e-9
    if abs(math.cos(angle)) < 1e-9 or abs(math.sin(angle)) < 1e-9:  # along an axis: the whole margin
        assert grown.depth(point + fraction * margin * normal) > -1e-9


def test_an_inflated_circle_grows_by_exactly_the_margin():
    circle = Ellipse((0.0, 0.0), (0.6, 0.6)).inflated(0.05)
    assert circle.depth((0.0, 0.649)) > 0 > circle.depth((0.651, 0.0))


@pytest.mark.parametrize("name", ["box", "triangle", "clockwise"])
def test_an_inflated_polygon_holds_exactly_the_points_within_the_margin_of_its_edges(name):
    polygon, margin = REGIONS[name], 0.3
    grown = polygon.inflated(margin)
    planes, grown_planes = polygon.half_planes(), grown.half_planes()
    np.testing.assert_allclose(grown_planes[:, :2], planes[:, :2], atol=1e-12)  # the same edge directions
    np.testing.assert_allclose(grown_planes[:, 2], planes[:, 2] + margin, atol=1e-12)  # each moved out by margin
    rng = np.random.default_rng(0)
    for point in rng.uniform(-4, 4, size=(2000, 2)):
        # the polygon's depth is the signed distance to its nearest edge line: > -margin within the margin
        inside_grown = grown.depth(point) > 0
        assert inside_grown == (polygon.depth(point) > -margin) or abs(polygon.depth(point) + margin) < 1e-9
    assert polygon.inflated(0.0) is polygon
