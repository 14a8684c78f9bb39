"""The README is a front door whose example runs as written; docs/reference.md's lists of names are exactly
what the package installs and emits (its parameter tables: test_settings_schema.py)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np

from nmpc_avoid_ros import cli
from nmpc_avoid_ros.core.sample.status import StepStatus

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
REFERENCE = (ROOT / "docs" / "reference.md").read_text()

#: the README's length limit: what it is, the two commands, the live example, the core example, where next
README_MAX_LINES = 150


def reference_section(heading: str) -> str:
    """docs/reference.md from `heading` (a whole line) to the next heading of the same or a higher level."""
    level = heading.split()[0]
    start = REFERENCE.index(f"\n{heading}\n")
    end = re.compile(rf"^#{{1,{len(level)}}} ", re.MULTILINE).search(REFERENCE, start + len(heading) + 2)
    return REFERENCE[start: end.start() if end else len(REFERENCE)]


def first_column(section: str) -> list[str]:
    """The `names` in the first column of a markdown table's body rows."""
    return re.findall(r"^\| `([^`]+)` \|", section, re.MULTILINE)


def reference_diagnostic_keys() -> set[str]:
    """The diagnostics values docs/reference.md promises (its **Diagnostics** paragraph)."""
    paragraph = REFERENCE[REFERENCE.index("**Diagnostics**"):]
    paragraph = paragraph[: paragraph.index("\n\n")]
    return set(re.findall(r"`([a-z_]+)`", paragraph))


def setup_executables() -> tuple[str, ...]:
    """setup.py's EXECUTABLES (each is installed as a console script `name = nmpc_avoid_ros.cli:name_main`)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    (value,) = [node.value for node in ast.walk(tree) if isinstance(node, ast.Assign)
                and any(isinstance(t, ast.Name) and t.id == "EXECUTABLES" for t in node.targets)]
    return ast.literal_eval(value)


def readme_python_example() -> str:
    """The README's one fenced python block, as written."""
    (block,) = re.findall(r"^```python\n(.*?)^```$", README, re.MULTILINE | re.DOTALL)
    return block


def test_the_readme_is_a_front_door_and_points_where_to_go_next():
    assert len(README.splitlines()) <= README_MAX_LINES
    assert "make demo" in README and "make test" in README
    links = set(re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README))
    assert {"docs/usage.md", "docs/reference.md", "docs/design.md", "BENCHMARKS.md", "docs/campaign/README.md"} <= links
    assert [link for link in links if not (ROOT / link).exists()] == []
    for heading in re.findall(r"\]\(docs/(?:usage|reference)\.md#([^)]+)\)", README):  # the anchors exist
        assert heading in {re.sub(r"[^a-z0-9 _-]", "", h.lower()).replace(" ", "-")
                           for h in re.findall(r"^#+ (.*)$", (ROOT / "docs" / "usage.md").read_text() + REFERENCE,
                                               re.MULTILINE)}, heading


def test_the_readme_nmpc_controller_example_runs_as_written(capsys):
    """The plain-Python example: state in, command out, an obstacle added; it reaches the target around it."""
    from nmpc_avoid_ros.core.problem.regions import Ellipse

    code = readme_python_example()
    assert len(code.splitlines()) <= 15 and "import rclpy" not in code
    scope: dict = {"__name__": "readme_example"}
    exec(compile(code, str(ROOT / "README.md"), "exec"), scope)
    x, result, controller = scope["x"], scope["result"], scope["controller"]
    assert abs(x[0] - 5.0) < 1e-2 and abs(x[1]) < 1e-2, x
    assert result.status is StepStatus.OK and abs(result.y_a[0] - 5.0) < 1e-2
    assert controller.regions and isinstance(scope["ellipse"], Ellipse)
    assert np.asarray(result.u).shape == (1,)
    assert "status ok" in capsys.readouterr().out


def test_reference_executables_are_what_setup_py_installs_and_cli_runs():
    documented = first_column(reference_section("## Executables"))
    installed = setup_executables()
    assert sorted(documented) == sorted(installed) == sorted(cli.COMMANDS)
    for name in installed:  # the console script's target exists and dispatches to that command
        entry = getattr(cli, f"{name}_main")
        assert callable(entry) and entry.__name__ == f"{name}_main"


def test_reference_lists_every_step_status():
    statuses = re.search(r"`status` \(([^)]*)\)", REFERENCE).group(1)
    assert set(re.findall(r"`([a-z_]+)`", statuses)) == {status.value for status in StepStatus}


def test_reference_names_the_counters_the_controller_publishes():
    keys = reference_diagnostic_keys()
    assert {"status", "nlp_builds", "samples", "fallbacks", "stale"} <= keys  # the parser found the paragraph


def test_the_results_section_lists_every_kept_result_and_each_exists():
    rows = first_column(reference_section("## Results: where each one lives and which command made it"))
    listed = {path for row in rows for path in ROOT.glob(row)}
    assert len(rows) >= 4 and all((ROOT / row).is_file() for row in rows if "*" not in row), rows
    kept = set((ROOT / "bench").glob("results.*")) | {p for p in (ROOT / "docs" / "campaign").rglob("*") if p.is_file()}
    assert kept - listed == set()
    # every further campaign or sweep folder says what it ran and with which command
    folders = [d for d in (ROOT / "docs" / "campaign").iterdir() if d.is_dir()]
    assert [d.name for d in folders if not (d / "README.md").is_file()] == []
