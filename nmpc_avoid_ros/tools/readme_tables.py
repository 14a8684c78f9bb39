"""The parameter tables of docs/reference.md, written from the nodes' declarations.

    make readme                                          # rewrite the tables in docs/reference.md
    python -m nmpc_avoid_ros.tools.readme_tables --check  # exit 1 and show the difference if stale

The controller's rows come from core/config/settings.py (ControllerSettings and NodeSettings, declared
through core/config/schema.py), the plant's and recorder's from their ParamSpecs. Each table is the
block of `|` lines after the node's heading (### `name`) in docs/reference.md; test_settings_schema.py
fails while the reference and the declarations differ. README.md is the front door and lists no
parameter: both modes exit 1 while it has a parameter table row.
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

ROOT = Path(__file__).resolve().parents[2]
REFERENCE = ROOT / "docs" / "reference.md"
README = ROOT / "README.md"


def expected_tables() -> dict[str, str]:
    """node name -> its parameter table as the declarations give it."""
    return {"controller": markdown_table(settings_specs() + NODE_SPECS), "recorder": markdown_table(RECORDER_SPECS),
            "plant": markdown_table(PLANT_SPECS)}


def _table_span(text: str, node: str) -> tuple[int, int]:
    """Character span of the first table after the heading ### `node` (ValueError if absent)."""
    heading = re.search(rf"^### `{re.escape(node)}`\s*$", text, re.MULTILINE)
    if heading is None:
        raise ValueError(f"no heading ### `{node}`")
    table = re.compile(r"^\|.*\n(?:\|.*\n)*", re.MULTILINE).search(text, heading.end())
    if table is None:
        raise ValueError(f"no table after ### `{node}`")
    return table.span()


def reference_tables(text: str) -> dict[str, str]:
    """node name -> its parameter table as the reference has it."""
    return {node: text[slice(*_table_span(text, node))] for node in expected_tables()}


#: a parameter table's row: | `name` | default | read-only or run time | meaning |
PARAMETER_ROW = re.compile(r"^\| `\w+` \| .* \| (?:read-only|run time) \| .*\|$", re.MULTILINE)


def parameter_rows(text: str) -> list[str]:
    """The lines of `text` that are a parameter table's row (README.md must have none)."""
    return PARAMETER_ROW.findall(text)


def rewrite(text: str) -> str:
    """The reference text with every parameter table replaced by the declared one."""
    for node, table in expected_tables().items():
        start, end = _table_span(text, node)
        text = text[:start] + table + text[end:]
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="readme_tables", description=__doc__.splitlines()[0])
    parser.add_argument("reference", nargs="?", type=Path, default=REFERENCE)
    parser.add_argument("--readme", type=Path, default=README, help="the README that must list no parameter")
    parser.add_argument("--check", action="store_true", help="only compare; exit 1 if the reference is stale")
    args = parser.parse_args(argv)
    try:
        text = args.reference.read_text()
        new = rewrite(text)
        readme_rows = parameter_rows(args.readme.read_text()) if args.readme.is_file() else []
    except (OSError, ValueError) as exc:  # no docs here (an installed package), or no table in them
        print(f"readme_tables: {args.reference}: {exc}", file=sys.stderr)
        return 2
    for row in readme_rows:
        print(f"readme_tables: {args.readme} has a parameter row (they belong in {args.reference.name}): "
              f"{row[:60]}...", file=sys.stderr)
    if args.check:
        sys.stdout.writelines(difflib.unified_diff(text.splitlines(True), new.splitlines(True), "reference",
                                                   "declared"))
        return int(new != text or bool(readme_rows))
    args.reference.write_text(new)
    return int(bool(readme_rows))


if __name__ == "__main__":
    sys.exit(main())
