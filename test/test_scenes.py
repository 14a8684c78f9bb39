"""Scene files: parsing, one-line errors, and `simulate --scene` with prediction on and off."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from nmpc_avoid_ros.core.loop.scene import SceneError, load_scene
from nmpc_avoid_ros.core.problem.regions import Ellipse, Polygon
from nmpc_avoid_ros.tools import simulate

SCENES = Path(__file__).resolve().parents[1] / "config" / "scenes"
SHIPPED = ("crossing_walker", "head_on", "closing_gap")

GOOD = """
scene:
  config: mobile_robot.yaml
  x0: [-8.0, -6.0, 0.0, 0.0]
  steps: 12
  plant: euler
  targets:
    - {t: 0.0, y: [8.0, 6.0]}
    - {t: 2.0, y: [0.0, 0.0]}
  obstacles:
    - {id: walker, t: 0.5, until: 25.0, shape: ellipse, center: [0.0, -4.0], semi_axes: [0.7, 0.7], yaw: 0.0,
       velocity: [0.0, 0.4], frame: output}
    - {id: cart, shape: box, center: [3.0, 3.0], size: [1.0, 0.5], velocity: [-0.2, 0.0], frame: output}
    - {id: wall, shape: polygon, vertices: [[5, -1], [6, -1], [6, 1]], frame: output}
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "scene.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_scenes_parse(name):
    scene = load_scene(SCENES / f"{name}.yaml")
    assert scene.config.name == "mobile_robot.yaml" and scene.obstacles
    assert all(o.region.moving for o in scene.obstacles)


def test_schedule_of_targets_and_obstacles(tmp_path):
    scene = load_scene(write(tmp_path, GOOD))
    assert scene.target_at(0.0) == (8.0, 6.0) and scene.target_at(1.99) == (8.0, 6.0)
    assert scene.target_at(2.0) == (0.0, 0.0)
    assert [n for n, _ in scene.named_regions_at(0.0)] == ["cart", "wall"]  # the walker appears at 0.5
    walker = dict(scene.named_regions_at(3.0))["walker"]
    assert isinstance(walker, Ellipse) and walker.center == pytest.approx((0.0, -4.0 + 0.4 * 2.5))
    assert walker.stamp == 3.0 and walker.velocity == (0.0, 0.4)
    assert isinstance(dict(scene.named_regions_at(3.0))["wall"], Polygon)
    assert "walker" not in dict(scene.named_regions_at(25.0))


@pytest.mark.parametrize("change, message", [
    (("steps: 12", "steps: many"), "scene.steps: expected an integer"),
    (("velocity: [0.0, 0.4]", "velocity: [0.0, .nan]"), "scene.obstacles[0].velocity: values must be finite"),
    (("velocity: [0.0, 0.4]", "velocity: [0.4]"), "scene.obstacles[0].velocity: expected 2 numbers"),
    (("shape: ellipse", "shape: blob"), "scene.obstacles[0].shape: must be one of"),
    (("semi_axes: [0.7, 0.7]", "semi_axes: [0.7, -1]"), "scene.obstacles[0]: ellipse semi-axes must be positive"),
    (("until: 25.0", "until: 0.1"), "scene.obstacles[0].until: must be later"),
    (("size: [1.0, 0.5], ", ""), "scene.obstacles[1].size: missing"),
    (("config: mobile_robot.yaml", "config: nowhere.yaml"), "scene.config: cannot find"),
    (("plant: euler", "plant: magic"), "scene.plant: must be one of"),
    (("frame: output}", "frame: map}"), "scene.obstacles[0]: frame must be one of"),
    (("yaw: 0.0,", "speed: 3,"), "scene.obstacles[0]: unknown key(s) speed"),
    (("{t: 2.0, y: [0.0, 0.0]}", "{t: 2.0, y: [0.0]}"), "scene.targets: every y must have the same length"),
    (("steps: 12", "steps: 12\n  x0: [1"), "not valid YAML"),
])
def test_malformed_scene_gets_one_line_naming_the_key(tmp_path, change, message):
    with pytest.raises(SceneError) as info:
        load_scene(write(tmp_path, GOOD.replace(*change)))
    assert message in str(info.value) and "\n" not in str(info.value)


def test_simulate_cli_refuses_a_malformed_scene_in_one_line(tmp_path, capsys):
    assert simulate.main(["--scene", str(write(tmp_path, GOOD.replace("steps: 12", "steps: -3")))]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("simulate: error: scene.steps:") and "\n" not in err


@pytest.mark.slow
def test_simulate_scene_writes_poses_and_clearances_and_prediction_avoids_the_walker(tmp_path):
    """The crossing walker: with prediction the robot keeps out (1e-3); the static assumption walks into it."""
    report = {}
    for mode in ("on", "off"):
        out = tmp_path / f"{mode}.json"
        assert simulate.main(["--scene", str(SCENES / "crossing_walker.yaml"), "--predict-obstacles", mode,
                              "--json", str(out), "--steps", "44"]) == 0
        report[mode] = json.loads(out.read_text())
    on, off = report["on"], report["off"]
    assert len(on["info"]["obstacles"]) == len(on["x"]) == 45
    first, last = on["info"]["obstacles"][0]["walker"], on["info"]["obstacles"][-1]["walker"]
    assert first["center"] == [0.0, -4.0] and last["center"] == pytest.approx([0.0, -4.0 + 0.5 * 44 * 0.25])
    assert on["summary"]["predict_obstacles"] is True and off["summary"]["predict_obstacles"] is False
    assert on["summary"]["min_clearance"]["walker"] >= -1e-3
    assert off["summary"]["min_clearance"]["walker"] < -0.3
    assert math.isclose(on["summary"]["max_penetration"], max(0.0, -on["summary"]["min_clearance"]["walker"]))
