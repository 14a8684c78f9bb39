"""ROS 2 message definitions as rosbag2 stores them in an MCAP schema (encoding ``ros2msg``).

The schema text of a type is its .msg file, then every nested type once, each introduced by a line
of 80 ``=`` and ``MSG: pkg/Type``. The .msg files are found under ``share/<pkg>/msg`` of the venv
and of AMENT_PREFIX_PATH, so no ROS distribution is needed.
"""

from __future__ import annotations

import functools
import os
import re
import sys
from collections.abc import Iterable
from pathlib import Path

from .mcap_io import BagError

SEPARATOR = "=" * 80
BUILTIN_TYPES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
    "int64", "uint64", "string", "wstring",
})
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_ARRAY_SUFFIX = re.compile(r"\[[^\]]*\]$")


def normalize_type(type_name: str) -> tuple[str, str]:
    """``pkg/msg/Type`` or ``pkg/Type`` -> (pkg, Type); BagError for anything else."""
    parts = type_name.strip().split("/")
    if len(parts) == 3 and parts[1] == "msg":
        parts = [parts[0], parts[2]]
    if len(parts) != 2 or not all(_NAME.match(p) for p in parts):
        raise BagError(f"not a ROS message type name: {type_name!r} (expected pkg/msg/Type)")
    return parts[0], parts[1]


def msg_search_paths() -> list[Path]:
    """Prefixes whose ``share/<pkg>/msg/<Type>.msg`` hold definitions: the venv, then AMENT_PREFIX_PATH."""
    prefixes = [Path(sys.prefix)]
    prefixes += [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    seen: list[Path] = []
    for p in prefixes:
        if p not in seen:
            seen.append(p)
    return seen


@functools.cache
def _msg_file_text(pkg: str, name: str, prefixes: tuple[Path, ...]) -> str:
    for prefix in prefixes:
        path = prefix / "share" / pkg / "msg" / f"{name}.msg"
        if path.is_file():
            return path.read_text(encoding="utf-8")
    where = ", ".join(str(p / "share" / pkg / "msg") for p in prefixes)
    raise BagError(f"no definition {name}.msg of {pkg}/msg/{name} under {where}")


def field_dependencies(text: str, pkg: str) -> list[str]:
    """Nested message types (``pkg/Type``) used by the fields of a .msg text, in order of appearance.

    Comments, blank lines, constants (``uint8 A=1``) and default values (``float64 x 0.5``) are
    handled; arrays (``T[]``, ``T[3]``, ``T[<=3]``) and bounded strings (``string<=10``) reduce to
    their element type; ``Header`` means ``std_msgs/Header``.
    """
    deps: list[str] = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        base = _ARRAY_SUFFIX.sub("", line.split()[0]).split("<=")[0]
        if base in BUILTIN_TYPES:
            continue
        if base == "Header":
            dep = "std_msgs/Header"
        elif "/" in base:
            dep = "/".join(normalize_type(base))
        elif _NAME.match(base):
            dep = f"{pkg}/{base}"
        else:
            raise BagError(f"cannot parse the field type {base!r} on line {number} of a {pkg} message: {raw!r}")
        if dep not in deps:
            deps.append(dep)
    return deps


def message_definition(type_name: str, prefixes: Iterable[Path] | None = None) -> str:
    """The full ``ros2msg`` schema text of a type, exactly as rosbag2 builds it.

    The type's own .msg text, then, depth first in order of first use, each nested type once:
    a line of 80 ``=``, a line ``MSG: pkg/Type`` and that type's .msg text.
    """
    prefixes = tuple(prefixes) if prefixes is not None else tuple(msg_search_paths())
    pkg, name = normalize_type(type_name)
    root = _msg_file_text(pkg, name, prefixes)
    parts = [root]
    seen = {f"{pkg}/{name}"}

    def append(dep: str) -> None:
        dep_pkg, dep_name = normalize_type(dep)
        text = _msg_file_text(dep_pkg, dep_name, prefixes)
        if not parts[-1].endswith("\n"):
            parts.append("\n")
        parts.append(f"{SEPARATOR}\nMSG: {dep}\n{text}")
        for sub in field_dependencies(text, dep_pkg):
            if sub not in seen:
                seen.add(sub)
                append(sub)

    for dep in field_dependencies(root, pkg):
        if dep not in seen:
            seen.add(dep)
            append(dep)
    return "".join(parts)
