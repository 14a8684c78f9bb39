"""Scan -> regions and grid window -> regions: wall time per call and the fit's accuracy, on synthetic input.

    python -m nmpc_avoid_ros.bench.perception --json bench/perception.json

Scenarios (the robot drives 4 m across the room at 1 m/s, 10 scans a second; beams see the room's walls,
two pillars and two walkers crossing at 0.5 and 0.8 m/s; ranges with Gaussian noise of 1 cm, 2 % of the
beams NaN):

- `scan_720`: a 720-beam, 360 degree scan (0.5 degree), the goal's case;
- `scan_1440`: the same at 0.25 degree;
- `grid`: a 20 m x 16 m grid at 5 cm with the same room, pillars (no walkers), a 5 m window.

Per call: `core_ms` the core pipeline alone (Perception.from_scan / from_grid: clean, cluster, fit, track; the
node's defaults: the nearest 6 circles and 3 wall segments kept), `core_cpu_ms` its CPU time (this thread: on a
shared machine the wall time also counts the waits for a core);
`node_ms` what the node's callback does with a message (ros/perception.py: ranges out of the message, the
pipeline, the markers built). Accuracy: the distance of each walker's fitted circle centre from the truth
and the estimated velocity's error, over the scans after the first 5 (m, m/s). Results: BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..core.perception.grid import Grid
from ..core.perception.raycast import cast, room
from ..core.perception.scan import Pose2D, ScanGeometry
from ..core.perception.sensing import Perception, PerceptionSettings
from ..core.problem.shapes import Ellipse
from .main import machine

PILLARS = ((1.5, 0.8, 0.3), (-2.5, 1.5, 0.2))
WALKERS = (((3.0, -1.0), (0.0, 0.5)), ((2.0, 2.0), (-0.8, 0.0)))  # (middle (m), velocity (m/s)), radius 0.3
WALKER_RADIUS = 0.3
NOISE = 0.01
DROPOUT = 0.02
RATE = 10.0


def _robot(k: int) -> Pose2D:
    """The robot's pose at scan k: from (-3, 0) along x at 1 m/s to (1, 0), and back."""
    t = (k / RATE) % 8.0
    return Pose2D(-3.0 + (t if t < 4.0 else 8.0 - t), 0.0, 0.0 if t < 4.0 else math.pi)


def _walkers(t: float) -> list[tuple[float, float, float]]:
    """The walkers (x, y, radius) at time t (s): each walks at its velocity for 3 s either side of its middle,
    then back (a triangle wave of slope +-1 s/s)."""
    there = 3.0 - abs((t % 12.0) - 6.0)
    return [(x0 + vx * there, y0 + vy * there, WALKER_RADIUS) for (x0, y0), (vx, vy) in WALKERS]


def _laser_scan(ranges: np.ndarray, geometry: ScanGeometry, stamp: float) -> Any:
    """The sensor_msgs/LaserScan a driver would send (ROS imported here only: the core part runs without it)."""
    from sensor_msgs.msg import LaserScan

    from ..ros.conversions import seconds_to_time

    msg = LaserScan(angle_min=geometry.angle_min, angle_max=geometry.angle_max,
                    angle_increment=geometry.angle_increment, range_min=geometry.range_min,
                    range_max=geometry.range_max, ranges=ranges.astype(np.float32).tolist())
    msg.header.stamp, msg.header.frame_id = seconds_to_time(stamp), "base_scan"
    return msg


def _timed(call: Callable[[], Any], cpu: list[float] | None = None) -> tuple[Any, float]:
    """(call's result, its wall time in ms); its CPU time (ms, this thread) appended to `cpu`: on a shared
    machine the wall time includes waiting for a core, the CPU time does not."""
    start, start_cpu = time.perf_counter(), time.thread_time()
    out = call()
    if cpu is not None:
        cpu.append((time.thread_time() - start_cpu) * 1e3)
    return out, (time.perf_counter() - start) * 1e3


def _stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values)
    return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max()), "count": len(a)}


def scan_scenario(beams: int, scans: int, seed: int = 1) -> dict[str, Any]:
    """`scans` scans of `beams` beams around the moving robot: timings and the walkers' fit accuracy."""
    from ..ros.perception import scan_geometry, scan_ranges, tracked_markers

    rng = np.random.default_rng(seed)
    increment = 2 * math.pi / beams
    geometry = ScanGeometry(-math.pi, -math.pi + increment * (beams - 1), increment, 0.05, 30.0)
    angles = geometry.angle_min + increment * np.arange(beams)
    walls = room(5.0, 3.5)
    core, node = Perception(), Perception()  # the node's defaults: 6 circles, 3 wall segments
    core_ms, core_cpu_ms, node_ms, centre_error, speed_error = [], [], [], [], []
    for k in range(scans):
        t = k / RATE
        robot, walkers = _robot(k), _walkers(t)
        ranges = cast(robot, angles, walls, [*PILLARS, *walkers], geometry.range_max)
        ranges = ranges + rng.normal(0.0, NOISE, beams)
        ranges[rng.random(beams) < DROPOUT] = np.nan
        seen, ms = _timed(lambda: core.from_scan(ranges, geometry, robot, t), core_cpu_ms)  # noqa: B023 - called now
        core_ms.append(ms)
        msg = _laser_scan(ranges, geometry, t)
        _, ms = _timed(lambda: tracked_markers(  # noqa: B023 - called at once
            node.from_scan(scan_ranges(msg), scan_geometry(msg), robot, t).regions, (), "scan", msg.header.stamp,  # noqa: B023
            "odom", 1.0))
        node_ms.append(ms)
        if k >= 5:
            circles = [r for _, r in seen.regions if isinstance(r, Ellipse)]
            for index, (x, y, _) in enumerate(walkers):
                if not circles:
                    break
                best = min(circles, key=lambda e: math.dist(e.center, (x, y)))  # noqa: B023
                if math.dist(best.center, (x, y)) < 0.3:  # seen (not hidden behind a pillar)
                    centre_error.append(math.dist(best.center, (x, y)))
                    truth = np.subtract(_walkers(t + 1e-3)[index][:2], (x, y)) / 1e-3
                    speed_error.append(float(np.linalg.norm(np.subtract(best.velocity, truth))))
    return {"beams": beams, "scans": scans, "core_ms": _stats(core_ms), "core_cpu_ms": _stats(core_cpu_ms),
            "node_ms": _stats(node_ms),
            "walker_centre_error_m": _stats(centre_error), "walker_velocity_error_m_s": _stats(speed_error)}


def grid_scenario(calls: int) -> dict[str, Any]:
    """The room as a 5 cm grid; a refit per robot position along its path."""
    resolution = 0.05
    cells = np.zeros((320, 400), dtype=np.int8)
    origin = Pose2D(-10.0, -8.0, 0.0)
    centres = origin.apply(np.stack(np.meshgrid((np.arange(400) + 0.5) * resolution,
                                                (np.arange(320) + 0.5) * resolution), axis=-1).reshape(-1, 2))
    x, y = centres.T
    on_wall = ((np.abs(np.abs(x) - 5.05) <= 0.05) & (np.abs(y) <= 3.6)) | (
        (np.abs(np.abs(y) - 3.55) <= 0.05) & (np.abs(x) <= 5.1))
    in_pillar = np.zeros_like(on_wall)
    for px, py, r in PILLARS:
        in_pillar |= np.hypot(x - px, y - py) <= r
    cells.ravel()[on_wall | in_pillar] = 100
    grid = Grid.from_fields(cells.ravel(), 400, 320, resolution, origin)
    perception, cpu = Perception(PerceptionSettings(half_window=5.0)), []
    times = [_timed(lambda k=k: perception.from_grid(grid, _robot(k), k / RATE), cpu)[1] for k in range(calls)]
    return {"cells": int(cells.size), "calls": calls, "core_ms": _stats(times), "core_cpu_ms": _stats(cpu)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench.perception", description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, required=True, help="write the records here")
    ap.add_argument("--scans", type=int, default=2000, help="scans per scan scenario")
    ap.add_argument("--grid-calls", type=int, default=300, help="grid windows fitted")
    args = ap.parse_args(argv)
    report: dict[str, Any] = {"machine": machine(), "scenarios": {
        "scan_720": scan_scenario(720, args.scans), "scan_1440": scan_scenario(1440, args.scans),
        "grid": grid_scenario(args.grid_calls)}}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=1))
    for name, record in report["scenarios"].items():
        line = [f"{name}: core median {record['core_ms']['median']:.3f} ms, p99 {record['core_ms']['p99']:.3f}, "
                f"max {record['core_ms']['max']:.3f} (CPU median {record['core_cpu_ms']['median']:.3f}, p99 "
                f"{record['core_cpu_ms']['p99']:.3f})"]
        if "node_ms" in record:
            line.append(f"node median {record['node_ms']['median']:.3f} ms, p99 {record['node_ms']['p99']:.3f}")
            line.append(f"walker centre error median {record['walker_centre_error_m']['median'] * 100:.2f} cm, "
                        f"p99 {record['walker_centre_error_m']['p99'] * 100:.2f} cm; velocity error median "
                        f"{record['walker_velocity_error_m_s']['median']:.3f} m/s, "
                        f"p90 {record['walker_velocity_error_m_s']['p90']:.3f}")
        print("; ".join(line), file=sys.stdout)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
