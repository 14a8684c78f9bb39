"""What a ROS user does: colcon build in a scratch workspace; executables and config installed."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from nmpc_avoid_ros.cli import COMMANDS

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
COLCON = Path(sys.executable).parent / "colcon"


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("ws")
    src = ws / "src" / "nmpc_avoid_ros"
    src.mkdir(parents=True)
    for name in ("package.xml", "setup.py", "setup.cfg", "resource", "config", "launch", "nmpc_avoid_ros"):
        (shutil.copytree if (ROOT / name).is_dir() else shutil.copy)(ROOT / name, src / name)
    env = dict(os.environ, AMENT_PREFIX_PATH=sys.prefix)
    res = subprocess.run([str(COLCON), "build"], cwd=ws, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    return ws / "install" / "nmpc_avoid_ros"


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_executables_land_where_ros2_run_looks_and_answer_help(installed, name):
    exe = installed / "lib" / "nmpc_avoid_ros" / name
    assert exe.is_file() and os.access(exe, os.X_OK)
    env = dict(os.environ, PYTHONPATH=str(next(installed.glob("lib/python3*/site-packages"))))
    res = subprocess.run([str(exe), "--help"], env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "usage" in res.stdout.lower(), res.stderr


def test_params_files_and_package_index_are_installed(installed):
    share = installed / "share"
    assert (share / "nmpc_avoid_ros" / "config" / "van_der_pol.yaml").is_file()
    assert (share / "nmpc_avoid_ros" / "config" / "mobile_robot.yaml").is_file()
    for scene in ("crossing_walker", "head_on", "closing_gap"):
        assert (share / "nmpc_avoid_ros" / "config" / "scenes" / f"{scene}.yaml").is_file()
    for name in ("config/unicycle.yaml", "config/unicycle.rviz", "config/unicycle.foxglove.json",
                 "launch/demo.launch.py", "launch/robot.launch.py", "config/worlds/room.yaml",
                 "config/worlds/room.pgm", "config/worlds/pillars.pgm"):
        assert (share / "nmpc_avoid_ros" / name).is_file(), name
    assert (share / "nmpc_avoid_ros" / "package.xml").is_file()
    assert (share / "ament_index" / "resource_index" / "packages" / "nmpc_avoid_ros").is_file()
