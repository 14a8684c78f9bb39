"""package.xml (what rosdep installs on a ROS machine) and requirements.txt (what the venv pins)
name the same dependencies; every ROS package depended on is a real one, and every message
package the code imports is depended on."""

from __future__ import annotations

import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from rosgraph import ROOT

#: requirements.txt distribution -> the rosdep key that installs it, verified to exist in
#: ros/rosdistro rosdep/python.yaml (commit 8468e88ccd); or None and why there is no key of its own
PIP_TO_ROSDEP: dict[str, str | None] = {
    "ros-jazzy-rclpy": "rclpy",  # a ROS package of the distribution (the wheels stand in for it)
    "ros-jazzy-common-interfaces": None,  # the message packages, each its own depend below
    "casadi": "casadi-pip",
    "numpy": "python3-numpy",
    "scipy": "python3-scipy",
    "matplotlib": "python3-matplotlib",
    "tqdm": "python3-tqdm",
    "pyyaml": "python3-yaml",
    "mcap-ros2-support": "mcap-ros2-support",
    "mcap": None,  # pulled by mcap-ros2-support
    "zstandard": None,  # pulled by mcap (chunk compression)
    "dask": None,  # no rosdep key: a package.xml comment says so
    "distributed": None,  # no rosdep key: a package.xml comment says so
    "do-mpc": "python3-do-mpc-pip",
    "pandas": None,  # pulled by do-mpc
    "rosbags": "python3-rosbags-pip",
    "pytest": "python3-pytest",
    "hypothesis": "python3-hypothesis",
    "ruff": None,  # the linter of `make test`, not a dependency of the package
    "pytest-xdist": None,  # `make test-core` on two processes only; colcon test runs one
    "colcon-core": None,  # build tool (colcon comes with a ROS installation)
    "colcon-ros": None,
    "colcon-python-setup-py": None,
    "wheel": None,  # build tool of the venv
    "playwright": None,  # the HTML report's browser test; no rosdep key: a package.xml comment says so
}
#: why a requirement has no key, as package.xml must say it in a comment
NO_KEY_COMMENTED = {"dask", "distributed", "playwright"}
#: ROS packages of the distribution that the PyPI wheels do not carry (ros2 launch only)
ROS_PACKAGES_NOT_IN_WHEELS = {"launch", "launch_ros"}


def requirements() -> set[str]:
    names = set()
    for line in (ROOT / "requirements.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            names.add(re.split(r"[\[=<>~!]", line)[0].strip().lower())
    return names


def package_xml() -> tuple[dict[str, set[str]], str]:
    """{tag: keys} of the depend tags, and the raw text (for comments)."""
    text = (ROOT / "package.xml").read_text()
    root = ET.fromstring(text)
    tags: dict[str, set[str]] = {}
    for element in root:
        if element.tag.endswith("depend"):
            tags.setdefault(element.tag, set()).add(element.text.strip())
    return tags, text


def ament_packages() -> set[str]:
    """ROS packages the venv's wheels provide (their ament index)."""
    return {p.name for p in (Path(sys.prefix) / "share" / "ament_index" / "resource_index" / "packages").iterdir()}


def test_every_pinned_requirement_has_a_decided_rosdep_key_and_package_xml_names_it():
    pinned = requirements()
    assert pinned == set(PIP_TO_ROSDEP), (pinned ^ set(PIP_TO_ROSDEP))  # a new pin needs a decision here
    tags, text = package_xml()
    declared = set().union(*tags.values())
    keys = {key for key in PIP_TO_ROSDEP.values() if key}
    assert keys <= declared, keys - declared
    comments = " ".join(re.findall(r"<!--(.*?)-->", text, re.S))
    for name in NO_KEY_COMMENTED:
        assert name in comments, name
    # the keys of the issue that rosdep does not have are gone
    assert not declared & {"python3-casadi-pip", "python3-mcap-pip", "python3-zstandard"}


def test_every_depend_is_a_ros_package_or_a_mapped_key():
    tags, _ = package_xml()
    declared = set().union(*tags.values())
    mapped = {key for key in PIP_TO_ROSDEP.values() if key}
    ros_packages = declared - mapped
    assert ros_packages <= ament_packages() | ROS_PACKAGES_NOT_IN_WHEELS, ros_packages - ament_packages()


def test_every_message_package_the_code_imports_is_an_exec_depend():
    tags, _ = package_xml()
    imported = set()
    for path in (ROOT / "nmpc_avoid_ros").rglob("*.py"):
        imported |= set(re.findall(r"^\s*from (\w+_(?:msgs|interfaces))\b", path.read_text(), re.M))
    assert imported and imported <= tags["exec_depend"], imported - tags["exec_depend"]
