"""The README's parameter tables, written from the nodes' declarations.

    make readme                                          # rewrite the tables in README.md
    python -m nmpc_avoid_ros.tools.readme_tables --check  # exit 1 and show the difference if stale

The controller's rows come from core/config/settings.py (ControllerSettings and NodeSettings, declared
through core/config/schema.py), the plant's and recorder's from their ParamSpecs. Each table is the
block of `|` lines after the node's heading (### `name`) in README.md; test_settings_schema.py
fails while README and declarations differ.
"""

from __future__ import annotations

import argparse
import difflib
import re
import sys
from pathlib import Path

from ..nodes.controller import NODE_SPECS
from ..nodes.plant import PLANT_SPECS
from ..nodes.recorder import RECORDER_SPECS
from ..ros.parameters import markdown_table, settings_specs

README = Path(__file__).resolve().parents[2] / "README.md"


def expected_tables() -> dict[str, str]:
    """node name -> its parameter table as the declarations give it."""
    return {"controller": markdown_table(settings_specs() + NODE_SPECS), "recorder": markdown_table(RECORDER_SPECS),
            "plant": markdown_table(PLANT_SPECS)}


def _table_span(text: str, node: str) -> tuple[int, int]:
    """Character span of the first table after the heading ### `node` (ValueError if absent)."""
    heading = re.search(rf"^### `{re.escape(node)}`\s*$", text, re.MULTILINE)
    if heading is None:
        raise ValueError(f"README has no heading ### `{node}`")
    table = re.compile(r"^\|.*\n(?:\|.*\n)*", re.MULTILINE).search(text, heading.end())
    if table is None:
        raise ValueError(f"README has no table after ### `{node}`")
    return table.span()


def readme_tables(text: str) -> dict[str, str]:
    """node name -> its parameter table as the README has it."""
    return {node: text[slice(*_table_span(text, node))] for node in expected_tables()}


def rewrite(text: str) -> str:
    """The README text with every parameter table replaced by the declared one."""
    for node, table in expected_tables().items():
        start, end = _table_span(text, node)
        text = text[:start] + table + text[end:]
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="readme_tables", description=__doc__.splitlines()[0])
    parser.add_argument("readme", nargs="?", type=Path, default=README)
    parser.add_argument("--check", action="store_true", help="only compare; exit 1 if the README is stale")
    args = parser.parse_args(argv)
    try:
        text = args.readme.read_text()
        new = rewrite(text)
    except (OSError, ValueError) as exc:  # no README here (an installed package), or no table in it
        print(f"readme_tables: {exc}", file=sys.stderr)
        return 2
    if args.check:
        sys.stdout.writelines(difflib.unified_diff(text.splitlines(True), new.splitlines(True), "README", "declared"))
        return int(new != text)
    args.readme.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
