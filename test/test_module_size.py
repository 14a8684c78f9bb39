"""No module of the package is over 500 lines, none of core over 400 (docs/design.md: split a module along a seam
instead)."""

from __future__ import annotations

from pathlib import Path

import pytest

import nmpc_avoid_ros

MAX_LINES = 500
#: core is what the next engineer reads first: its rooms stay smaller
MAX_CORE_LINES = 400
PACKAGE_DIR = Path(nmpc_avoid_ros.__file__).parent
MODULES = sorted(PACKAGE_DIR.rglob("*.py"))


def test_the_size_check_sees_every_layer():
    layers = {m.relative_to(PACKAGE_DIR).parts[0] for m in MODULES}
    assert {"core", "ros", "bag", "nodes", "evaluation", "tools", "bench"} <= layers
    assert len(MODULES) > 50


@pytest.mark.parametrize("module", MODULES, ids=lambda m: str(m.relative_to(PACKAGE_DIR)))
def test_module_is_at_most_500_lines(module: Path):
    lines = len(module.read_text(encoding="utf-8").splitlines())
    limit = MAX_CORE_LINES if module.relative_to(PACKAGE_DIR).parts[0] == "core" else MAX_LINES
    assert lines <= limit, f"{module.relative_to(PACKAGE_DIR)} has {lines} lines (split it along a seam)"
