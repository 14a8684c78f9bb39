"""A body for the planar robots: footprint_radius, or a footprint polygon approximated by its circumscribed disc
about base_link (settings.body_radius); obstacles are planned around grown by region_margin + body_radius
(settings.planning_margin), and analyze reports the body's clearance beside the reference point's."""

from __future__ import annotations

import json
import math

import pytest
import yaml
from rosgraph import ROOT
from test_analyze_truth import _robot_bag

from nmpc_avoid_ros.core.config.settings import ControllerSettings
from nmpc_avoid_ros.core.errors import ConfigError
from nmpc_avoid_ros.tools.analyze import main as analyze_main

#: a 0.6 m x 0.4 m robot with base_link 0.1 m behind its middle
RECTANGLE = (0.4, 0.2, -0.2, 0.2, -0.2, -0.2, 0.4, -0.2)


def test_the_body_radius_is_the_footprint_radius_or_the_polygons_circumscribed_one():
    assert ControllerSettings().body_radius == 0.0 and ControllerSettings().planning_margin == 0.0
    assert ControllerSettings(footprint_radius=0.25).body_radius == 0.25
    # the farthest corner from base_link: (0.4, +-0.2)
    assert ControllerSettings(footprint=RECTANGLE).body_radius == pytest.approx(math.hypot(0.4, 0.2))
    both = ControllerSettings(footprint=RECTANGLE, footprint_radius=0.5, region_margin=0.05)
    assert both.body_radius == 0.5 and both.planning_margin == pytest.approx(0.55)


@pytest.mark.parametrize("footprint", [(0.1, 0.2), (0.1, 0.2, 0.3, 0.4), (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)])
def test_a_footprint_that_is_no_polygon_is_refused(footprint):
    with pytest.raises(ConfigError, match="footprint"):
        ControllerSettings(footprint=footprint)
    with pytest.raises(ConfigError, match="footprint_radius"):
        ControllerSettings(footprint_radius=-0.1)


def test_analyze_reports_the_bodys_clearance_the_reference_points_less_its_radius(tmp_path):
    """The robot bag of test_analyze_truth passes 0.3 m from a circle: a 0.2 m body keeps 0.1 m."""
    _robot_bag(tmp_path / "robot.mcap")
    params = yaml.safe_load((ROOT / "config" / "unicycle.yaml").read_text())
    (section,) = [key for key in params if key.endswith("controller")]
    params[section]["ros__parameters"]["footprint_radius"] = 0.2
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    assert analyze_main([str(tmp_path / "robot.mcap"), "--out", str(tmp_path / "o"), "--config",
                         str(tmp_path / "params.yaml")]) == 0
    (metrics,) = json.loads((tmp_path / "o" / "metrics.json").read_text())["bags"]
    clearance = metrics["clearance"]
    assert clearance["body_radius"] == 0.2
    truth = clearance["recorded_states"]
    assert truth["min_obstacle_distance"] == pytest.approx(0.3, abs=1e-12)
    assert truth["min_body_distance"] == pytest.approx(0.1, abs=1e-12)
    for view in ("at_samples", "resimulated_between_samples"):
        entry = clearance[view]
        assert entry["min_body_distance"] == pytest.approx(entry["min_obstacle_distance"] - 0.2, abs=1e-12)


def test_the_controller_plans_around_every_region_grown_by_the_body():
    from nmpc_avoid_ros.core.problem.shapes import Ellipse, rotated_box
    from nmpc_avoid_ros.core.sample.controller import NmpcController

    controller = NmpcController(ControllerSettings(max_ellipses=1, max_polygons=1, footprint_radius=0.3,
                                                   region_margin=0.05))
    controller.set_regions([Ellipse((1.0, 0.5), (0.5, 0.5)), rotated_box((-2.0, 0.0), (1.0, 0.4))])
    circle, box = controller.planned_regions
    assert circle.semi_axes == pytest.approx((0.85, 0.85))
    assert box.depth((-2.0, 0.2 + 0.35 - 1e-9)) > 0 > box.depth((-2.0, 0.2 + 0.35 + 1e-9))
    assert controller.regions[0].semi_axes == (0.5, 0.5)  # as given: the clearance is measured against these
    controller.update_settings(footprint_radius=0.4)  # a run-time change re-packs the slots
    assert controller.planned_regions[0].semi_axes == pytest.approx((0.95, 0.95))
