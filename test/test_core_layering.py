"""Layers: `core` never imports ROS (rclpy or any message package), and the package layers depend one way
(docs/design.md section 2)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import nmpc_avoid_ros.core as core

ROS_MODULES = ("rclpy", "std_msgs", "geometry_msgs", "visualization_msgs", "diagnostic_msgs", "nav_msgs",
               "rosgraph_msgs", "builtin_interfaces", "rcl_interfaces", "sensor_msgs", "rosidl_runtime_py")
CORE_DIR = Path(core.__file__).parent


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_core_sources_import_no_ros_module():
    files = sorted(CORE_DIR.rglob("*.py"))
    assert len(files) >= 6
    offenders = {str(f.relative_to(CORE_DIR)): sorted(imported_modules(f) & set(ROS_MODULES)) for f in files}
    assert {k: v for k, v in offenders.items() if v} == {}


def test_importing_all_of_core_loads_no_ros_module():
    modules = [".".join(("nmpc_avoid_ros", "core", *f.relative_to(CORE_DIR).with_suffix("").parts))
               for f in CORE_DIR.rglob("*.py") if f.stem != "__init__"]
    code = (
        "import sys\n"
        + "".join(f"import {m}\n" for m in modules)
        + f"bad = [m for m in sys.modules if m.split('.')[0] in {ROS_MODULES!r}]\n"
        + "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


PACKAGE_DIR = CORE_DIR.parent
#: layer -> the sibling layers it must not import (core <- ros <- bag <- nodes, evaluation, tools)
FORBIDDEN = {"core": {"ros", "bag", "nodes", "evaluation", "tools", "bench"},
             "ros": {"bag", "nodes", "evaluation", "tools", "bench"},
             "bag": {"nodes", "evaluation", "tools", "bench"},
             "evaluation": {"nodes", "tools"}}


def package_imports(path: Path) -> set[str]:
    """The first-level subpackages of nmpc_avoid_ros that a module imports (absolute or relative)."""
    parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts  # ('nmpc_avoid_ros', 'bag', 'x')
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = list(parts[:-node.level]) if node.level else []
            module = [*base, *(node.module.split(".") if node.module else [])]
            if module[:1] == ["nmpc_avoid_ros"]:
                names.add(module[1] if len(module) > 1 else node.names[0].name)
        elif isinstance(node, ast.Import):
            names.update(a.name.split(".")[1] for a in node.names if a.name.startswith("nmpc_avoid_ros."))
    return names


def test_layers_depend_one_way():
    offenders = {}
    for layer, forbidden in FORBIDDEN.items():
        files = sorted((PACKAGE_DIR / layer).rglob("*.py"))
        assert files, layer
        for f in files:
            bad = package_imports(f) & forbidden
            if bad:
                offenders[str(f.relative_to(PACKAGE_DIR))] = sorted(bad)
    assert offenders == {}


def test_the_layer_check_sees_relative_imports():
    probe = PACKAGE_DIR / "evaluation" / "campaign" / "scoring.py"
    assert {"core"} <= package_imports(probe)
    assert "tools" in package_imports(PACKAGE_DIR / "bench" / "node.py")


#: the rooms of core in their order: each imports only rooms before it (core/__init__.py)
ROOMS = ("problem", "perception", "config", "nlp", "sample", "loop")


def core_rooms_imported(path: Path) -> set[str]:
    """The rooms of core a core module imports (relative imports, also inside functions)."""
    parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts  # ('nmpc_avoid_ros', 'core', room, x)
    rooms: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level:
            module = [*parts[:-node.level], *(node.module.split(".") if node.module else [])]
            if module[:2] == ["nmpc_avoid_ros", "core"] and len(module) > 2 and module[2] in ROOMS:
                rooms.add(module[2])
    return rooms


def test_core_rooms_depend_one_way():
    assert sorted(p.name for p in CORE_DIR.iterdir() if p.is_dir() and p.name != "__pycache__") == sorted(ROOMS)
    offenders = {}
    for i, room in enumerate(ROOMS):
        for f in sorted((CORE_DIR / room).rglob("*.py")):
            later = core_rooms_imported(f) & set(ROOMS[i + 1:])
            if later:
                offenders[str(f.relative_to(CORE_DIR))] = sorted(later)
    assert offenders == {}
