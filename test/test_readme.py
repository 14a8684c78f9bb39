"""README claims that are lists of names: they must be exactly what the package installs and emits."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from nmpc_avoid_ros import cli
from nmpc_avoid_ros.core.sample.status import StepStatus

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def readme_section(heading: str) -> str:
    """The README text from `heading` (a whole line) to the next heading of the same or a higher level."""
    level = heading.split()[0]
    start = README.index(f"\n{heading}\n")
    end = re.compile(rf"^#{{1,{len(level)}}} ", re.MULTILINE).search(README, start + len(heading) + 2)
    return README[start: end.start() if end else len(README)]


def first_column(section: str) -> list[str]:
    """The `names` in the first column of a markdown table's body rows."""
    return re.findall(r"^\| `([^`]+)` \|", section, re.MULTILINE)


def readme_diagnostic_keys() -> set[str]:
    """The diagnostics values the README promises (its **Diagnostics** paragraph)."""
    paragraph = README[README.index("**Diagnostics**"):]
    paragraph = paragraph[: paragraph.index("\n\n")]
    return set(re.findall(r"`([a-z_]+)`", paragraph))


def setup_executables() -> tuple[str, ...]:
    """setup.py's EXECUTABLES (each is installed as a console script `name = nmpc_avoid_ros.cli:name_main`)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    (value,) = [node.value for node in ast.walk(tree) if isinstance(node, ast.Assign)
                and any(isinstance(t, ast.Name) and t.id == "EXECUTABLES" for t in node.targets)]
    return ast.literal_eval(value)


def test_readme_executables_are_what_setup_py_installs_and_cli_runs():
    documented = first_column(readme_section("## Executables"))
    installed = setup_executables()
    assert sorted(documented) == sorted(installed) == sorted(cli.COMMANDS)
    for name in installed:  # the console script's target exists and dispatches to that command
        entry = getattr(cli, f"{name}_main")
        assert callable(entry) and entry.__name__ == f"{name}_main"


def test_readme_lists_every_step_status():
    statuses = re.search(r"`status` \(([^)]*)\)", README).group(1)
    assert set(re.findall(r"`([a-z_]+)`", statuses)) == {status.value for status in StepStatus}


def test_readme_names_the_counters_the_controller_publishes():
    keys = readme_diagnostic_keys()
    assert {"status", "nlp_builds", "samples", "fallbacks", "stale"} <= keys  # the parser found the paragraph


def test_the_results_section_lists_every_kept_result_and_each_exists():
    rows = first_column(readme_section("## Results: where each one lives and which command made it"))
    listed = {path for row in rows for path in ROOT.glob(row)}
    assert len(rows) >= 4 and all((ROOT / row).is_file() for row in rows if "*" not in row), rows
    kept = set((ROOT / "bench").glob("results.*")) | {p for p in (ROOT / "docs" / "campaign").rglob("*") if p.is_file()}
    assert kept - listed == set()
    # every further campaign or sweep folder says what it ran and with which command
    folders = [d for d in (ROOT / "docs" / "campaign").iterdir() if d.is_dir()]
    assert [d.name for d in folders if not (d / "README.md").is_file()] == []
