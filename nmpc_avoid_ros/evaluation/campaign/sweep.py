"""`campaign --sweep NAME=V1,V2,...`: the same scenarios under several values of a run-time setting.

Only run-time settings (core.settings.RUNTIME_FIELDS: NLP parameters, changeable without a
rebuild) may be swept: a sweep compares the controller as it would be retuned in operation.
Each value runs as its own campaign in <out>/<NAME>=<V>/ (resumable like any other); the
comparison goes to sweep.json, sweep.md (one table per family) and sweep.png. A comparison
row is one summary key (summary.summarize); SWEEP_KEYS picks which.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...core.config.settings import RUNTIME_FIELDS, SETTINGS, ControllerSettings
from ...core.errors import ConfigError

#: summary keys compared across the values (table rows and figure panels)
SWEEP_KEYS = ("share_converged", "share_near", "share_near_admissible", "stop_short", "max_penetration",
              "runs_with_penetration_over_1e-3", "collision_rate", "runs_with_obstacle_penetration_over_1e-3",
              "max_penetration_obstacles", "min_clearance_obstacles", "min_clearance_obstacles_median",
              "penetration_after_first_step", "fallback_penetration",
              "fallbacks", "solver_failures", "recursive_feasibility_rate",
              "solve_ms_median_of_medians", "solve_ms_max", "certificate_violation_rate")


@dataclass(frozen=True)
class Sweep:
    name: str
    values: tuple[Any, ...]


def _split(text: str) -> list[str]:
    """Split on the commas outside brackets: '[1,2],[3,4]' -> ['[1,2]', '[3,4]']."""
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        depth += (ch == "[") - (ch == "]")
        if ch == "," and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return [p.strip() for p in parts]


def _assignment(option: str, text: str, form: str) -> tuple[str, str]:
    """'NAME=REST' -> (NAME, REST); ConfigError naming the option and the expected `form` if not."""
    match = re.fullmatch(r"\s*([A-Za-z_]\w*)\s*=(.+)", text)
    if not match:
        raise ConfigError(f"{option} {text!r}: expected {form}")
    return match.group(1), match.group(2).strip()


def parse_sweep(text: str, settings: Mapping[str, ControllerSettings]) -> Sweep:
    """NAME=V1,V2,... (JSON values) checked against every family's settings; ConfigError if not valid."""
    name, rest = _assignment("--sweep", text, "NAME=V1,V2,...")
    raw = _split(rest)
    if name not in RUNTIME_FIELDS:
        raise ConfigError(f"--sweep {name}: not a run-time setting (changing it rebuilds the NLP); "
                          f"run-time settings: {', '.join(sorted(RUNTIME_FIELDS))}")
    values = []
    for item in raw:
        try:
            values.append(json.loads(item))
        except json.JSONDecodeError:
            raise ConfigError(f"--sweep {name}: {item!r} is not a JSON value") from None
    if len(values) < 2 or len({json.dumps(v) for v in values}) != len(values):
        raise ConfigError(f"--sweep {name}: give at least two distinct values")
    for value in values:
        for fam, s in settings.items():
            try:
                s.replace(**{name: value})
            except (ConfigError, TypeError, ValueError) as exc:
                raise ConfigError(f"--sweep {name}={json.dumps(value)} ({fam}): {exc}") from None
    return Sweep(name, tuple(values))


def parse_settings(texts: Sequence[str]) -> dict[str, Any]:
    """`--set NAME=VALUE` items (JSON values; any controller setting, structural ones included) -> a
    mapping; ConfigError for a malformed item, an unknown name or a name given twice. The values are
    checked where the params files are read (`settings_from_params`)."""
    out: dict[str, Any] = {}
    for text in texts:
        name, raw = _assignment("--set", text, "NAME=VALUE")
        if name not in SETTINGS:
            raise ConfigError(f"--set {name}: not a controller setting")
        if name in out:
            raise ConfigError(f"--set {name}: given twice")
        try:
            out[name] = json.loads(raw)
        except json.JSONDecodeError:
            raise ConfigError(f"--set {name}: {raw!r} is not a JSON value (strings in double quotes)") from None
    return out


def sweep_dir(out: Path, name: str, value: Any) -> Path:
    """<out>/<NAME>=<V> with V as compact JSON (brackets and commas kept; spaces dropped)."""
    return out / f"{name}={json.dumps(value, separators=(',', ':'))}"


def _cell(value: Any) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.3g}"
    return str(value)


def write_sweep(out: Path, sweep: Sweep, results: Sequence[Mapping[str, Any]], plots: bool = True) -> str:
    """sweep.json, sweep.md and sweep.png from each value's campaign result; returns the markdown."""
    fams = list(dict.fromkeys(fam for r in results for fam in r["summary"]))
    table = {fam: {key: [r["summary"].get(fam, {}).get(key) for r in results] for key in SWEEP_KEYS} for fam in fams}
    labels = [json.dumps(v) for v in sweep.values]
    (out / "sweep.json").write_text(json.dumps({"name": sweep.name, "values": list(sweep.values),
                                                "summary": table}, indent=1))
    lines = []
    for fam in fams:
        lines += [f"{fam}: {sweep.name} sweep", "", f"| summary | {' | '.join(labels)} |",
                  "|---|" + "---|" * len(labels)]
        lines += [f"| {key} | {' | '.join(_cell(v) for v in row)} |" for key, row in table[fam].items()]
        lines.append("")
    text = "\n".join(lines)
    (out / "sweep.md").write_text(text)
    if plots:
        _figure(out / "sweep.png", sweep, labels, table)
    return text


def _figure(path: Path, sweep: Sweep, labels: list[str], table: Mapping[str, Mapping[str, list]]) -> None:
    from ...bag.figures import plt

    keys = ("share_converged", "share_near", "max_penetration", "fallbacks")
    fig, axes = plt.subplots(1, len(keys), figsize=(3.4 * len(keys), 3.2), dpi=100)
    width = 0.8 / max(1, len(table))
    for ax, key in zip(axes, keys):
        for j, (fam, rows) in enumerate(table.items()):
            vals = [float(v) if v is not None else float("nan") for v in rows[key]]
            ax.bar([i + j * width for i in range(len(labels))], vals, width, label=fam)
        ax.set_xticks([i + width * (len(table) - 1) / 2 for i in range(len(labels))], labels, fontsize=8)
        ax.set_title(key, fontsize=9)
        ax.set_xlabel(sweep.name)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
