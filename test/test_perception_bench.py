"""The perception benchmark end to end on a few scans (its numbers are BENCHMARKS.md's, not a test's)."""

from __future__ import annotations

import json

from nmpc_avoid_ros.bench.perception import main


def test_the_perception_bench_writes_timings_and_fit_accuracy(tmp_path, capsys):
    out = tmp_path / "perception.json"
    assert main(["--json", str(out), "--scans", "12", "--grid-calls", "3"]) == 0
    scenarios = json.loads(out.read_text())["scenarios"]
    assert set(scenarios) == {"scan_720", "scan_1440", "grid"}
    for record in scenarios.values():
        for key in ("core_ms", "core_cpu_ms"):
            assert 0 < record[key]["median"] <= record[key]["p99"] <= record[key]["max"]
    assert scenarios["scan_720"]["scans"] == 12 and scenarios["scan_720"]["walker_centre_error_m"]["count"] > 0
    assert "scan_720: core median" in capsys.readouterr().out
