"""The self-contained HTML report: one file, no network, its plots drawn by the vendored uPlot.

`write_report(path, runs)` embeds the runs' data (bag/report.py) as JSON in the page together with
uPlot (UPLOT_VERSION, the npm package `uplot`, MIT: bag/vendor/uPlot.LICENSE; its minified script
and style sheet inlined verbatim) and the glue script bag/report.js, so the file opens offline in
any browser. A slider scrubs through the samples: at sample k the plane shows the measured state,
the plan's predicted trajectory, x_a (from y_a), the target's steady state and the regions in
force, moving ones drawn where they are and, dashed, where the plan predicted them over the
horizon; cursors mark k on the time series, solve times, cost terms and the certificate.
`window.report` exposes the drawn sample (for the browser test).
"""

from __future__ import annotations

import html
import json
from importlib import resources
from pathlib import Path
from typing import Any

STYLE = """
body { font: 14px system-ui, sans-serif; margin: 16px; color: #222; max-width: 1400px; }
h1 { font-size: 20px; margin: 0 0 8px; }
#controls { display: flex; gap: 16px; align-items: center; margin: 8px 0; flex-wrap: wrap; }
#scrub { width: 520px; }
#grid { display: grid; grid-template-columns: 660px 660px; gap: 8px; }
.uplot { border: 1px solid #ddd; background: #fff; margin-bottom: 4px; }
.u-title { font-size: 13px; font-weight: normal; text-align: left; padding-left: 8px; }
.u-legend { font-size: 12px; }
#info { font-family: ui-monospace, monospace; font-size: 12px; white-space: pre; background: #f7f7f7;
        padding: 8px; border: 1px solid #ddd; min-height: 300px; }
table { border-collapse: collapse; font-size: 12px; margin-top: 8px; }
td, th { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
"""

#: the vendored uPlot's version (bag/vendor/uPlot.iife.min.js names it in its first line)
UPLOT_VERSION = "1.6.32"


def package_text(name: str) -> str:
    """A package data file of bag/ (setup.py package_data ships them)."""
    return resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


#: the page's script, embedded verbatim (a package data file, so it is plain JavaScript to edit and lint)
SCRIPT = package_text("report.js")
#: uPlot's script and style sheet, inlined as published so the page needs no network
UPLOT_SCRIPT, UPLOT_STYLE = package_text("vendor/uPlot.iife.min.js"), package_text("vendor/uPlot.min.css")

BODY = """
<h1>{title}</h1>
<div id="controls">
  <label>run <select id="run"></select></label>
  <input type="range" id="scrub" min="0" max="0" value="0" step="1" aria-label="sample">
  <span id="klabel"></span>
</div>
<div id="grid">
  <div id="plane"></div>
  <div id="info"></div>
  <div id="series"></div>
  <div>
    <div id="solve"></div>
    <div id="costs"></div>
    <div id="certificate"></div>
  </div>
</div>
<table><thead><tr><th>run</th><th>settling step</th><th>final error</th><th>max penetration</th>
<th>solve median ms</th><th>solve max ms</th><th>fallbacks</th><th>certificate violations</th><th>finished</th></tr>
</thead><tbody id="metrics"></tbody></table>
"""


def write_report(path: Path, runs: list[dict[str, Any]], title: str = "nmpc_avoid_ros run report") -> Path:
    """Write the page with `runs` (bag/report.report_data) embedded; returns the path."""
    data = json.dumps({"runs": runs}, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    page = (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
            f"<style>{UPLOT_STYLE}</style><style>{STYLE}</style></head><body>{BODY.format(title=html.escape(title))}"
            f"<script type=\"application/json\" id=\"report-data\">{data}</script>"
            f"<script>{UPLOT_SCRIPT}</script><script>{SCRIPT}</script></body></html>\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(page, encoding="utf-8")
    return path
