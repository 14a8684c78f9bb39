"""`replay`: republish a bag with its timing, re-solve the controller on it, or rerun its closed loop.

    python -m nmpc_avoid_ros replay BAG [--rate 2.0]                       # republish (needs ROS)
    python -m nmpc_avoid_ros replay BAG --resolve [--config FILE] [--mu 0] [--json OUT]
    python -m nmpc_avoid_ros replay BAG --closed-loop [--config FILE] [--mu X] [--kappa X] [--solver NAME]
        [--plant continuous|euler|rk4] [--timing recorded|ideal] [--json FILE] [--out DIR] [--sweep NAME=V1,V2,...]

Both offline modes take the controller settings from the bag (the parameters the recorder asked
the controller for) and `--closed-loop` also the plant (the plant node's model, integration and
sample time), so a replay with nothing changed reproduces the bag; `--config` and `--plant` replace
them. A plant that ran in real time is replayed with the loop's recorded timing (the plant's own
steps, and commands that reached it a step late, read from the recorded states; `--timing
ideal`: every sample lasts sample_time and its command holds from its start). A bag recorded
before the recorder kept parameters gets the shipped van_der_pol.yaml and a plant inferred from
the bag (no /clock: real time, so the continuous plant; /clock: the lockstep demo's euler plant),
and the output says so.

`--resolve` feeds the recorded states, targets and regions, sample by sample, to a fresh
controller built from the configuration (with overrides) and reports how its commands differ from
the recorded ones: "what would the new tuning have done on yesterday's run".

`--closed-loop` runs the loop again through the plant model from the state of the bag's first
solved sample, with the bag's timeline of targets, regions and run-time settings (mu, kappa as the
diagnostics recorded them; a flag overrides one for the whole run), so the states react to the
new tuning (evaluation/counterfactual.py). It prints the recorded and the counterfactual metrics
side by side; --json writes the run in simulate's format, --out DIR the overlaid figures and
metrics.json. --sweep runs one counterfactual per value of a run-time setting: a table (settling,
penetration, final error, solve times, certificate violations) and one overlaid phase portrait.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..bag.analysis import RecordedRun
from ..bag.mcap_io import BagError, load_bag
from ..core.config.settings import ControllerSettings
from ..core.errors import NmpcError
from ..core.loop.closed_loop import PLANT_INTEGRATIONS
from ..core.sample.controller import NmpcController
from .replay_closed_loop import closed_loop_main, describe_inputs, replay_inputs

LATCHED_TOPICS = ("target", "obstacles")


def resolve(run: RecordedRun, settings: ControllerSettings, tolerance: float = 1e-6) -> dict[str, Any]:
    """Re-run the controller on the recorded samples; per-step and summary differences of u."""
    controller = NmpcController(settings)
    steps = []
    for k in range(len(run.x)):
        controller.set_regions(run.regions[k])
        result = controller.step(run.x[k], run.targets[k], time=None if run.times is None else run.times[k])
        diff = float(np.max(np.abs(result.u - run.u[k])))
        steps.append({"step": k, "recorded_u": run.u[k].tolist(), "resolved_u": result.u.tolist(), "max_abs_diff": diff,
                      "status": result.status, "y_a": result.y_a.tolist()})
    diffs = np.array([s["max_abs_diff"] for s in steps])
    return {
        "steps": steps,
        "summary": {"samples": len(steps), "max_abs_diff": float(diffs.max()), "mean_abs_diff": float(diffs.mean()),
                    "steps_differing": int(np.sum(diffs > tolerance)), "tolerance": tolerance,
                    "first_differing_step": int(np.argmax(diffs > tolerance)) if np.any(diffs > tolerance) else None},
    }


def restamped(data: bytes, msg_type: type, shift_ns: int) -> Any:
    """A recorded MarkerArray with every non-zero marker stamp moved by `shift_ns`."""
    from rclpy.serialization import deserialize_message

    from ..ros.conversions import seconds_to_time, stamp_to_seconds

    msg = deserialize_message(bytes(data), msg_type)
    for marker in msg.markers:
        stamp = stamp_to_seconds(marker.header.stamp)
        if stamp:
            marker.header.stamp = seconds_to_time(stamp + shift_ns * 1e-9)
    return msg


def republish(bag: Path, rate: float, wait: float = 1.0) -> int:
    """Publish every recorded message on its topic, spaced by its log times divided by `rate`.

    At rate 1, the obstacles' marker stamps are shifted to the republishing clock (`restamped`).

    Publishers are made first and given `wait` seconds to be discovered, so the first messages
    are not published into an empty graph.
    """
    import rclpy

    from ..ros.parameters import LATCHED_QOS, STREAM_QOS

    recorded = load_bag(bag, decode=False)
    messages = sorted((t, topic, data) for topic, items in recorded.topics.items() for t, data in items)
    rclpy.init()
    node = rclpy.create_node("replay")
    publishers: dict[str, Any] = {}
    count = 0
    try:
        for topic, type_name in recorded.types.items():
            pkg, _, name = type_name.replace("/msg/", "/").partition("/")
            msg_type = getattr(importlib.import_module(f"{pkg}.msg"), name)
            qos = LATCHED_QOS if topic.rsplit("/", 1)[-1] in LATCHED_TOPICS else STREAM_QOS
            publishers[topic] = node.create_publisher(msg_type, topic, qos)
        time.sleep(wait)
        start_wall = time.monotonic()
        # stamped markers are moved to the republishing clock, so a live controller places moving
        # obstacles in time as it did when recording (their stamps are checked against receipt)
        shift_ns = node.get_clock().now().nanoseconds - messages[0][0] if messages else 0
        for log_time, topic, data in messages:
            delay = start_wall + (log_time - messages[0][0]) * 1e-9 / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if topic.rsplit("/", 1)[-1] == "obstacles" and rate == 1.0:
                publishers[topic].publish(restamped(data, publishers[topic].msg_type, shift_ns))
            else:
                publishers[topic].publish(bytes(data))  # the recorded CDR bytes, unchanged
            count += 1
        time.sleep(min(wait, 1.0))  # let reliable transport deliver the last ones
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print(f"replay: published {count} messages on {len(publishers)} topics"
          + ("" if recorded.finished else " (the file was not finished)"))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="replay", description=__doc__.split("\n\n")[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--rate", type=float, default=1.0, help="replay speed factor (republish mode)")
    ap.add_argument("--wait", type=float, default=1.0, help="seconds for discovery before republishing")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--resolve", action="store_true", help="re-solve the controller offline on the bag")
    mode.add_argument("--closed-loop", action="store_true",
                      help="rerun the closed loop from the bag's first state under the new tuning")
    ap.add_argument("--config", type=Path, help="params file (default: the controller parameters the bag recorded, "
                    "else the shipped van_der_pol.yaml)")
    ap.add_argument("--mu", type=float, help="override mu (the whole run)")
    ap.add_argument("--kappa", type=float, help="override kappa (the whole run)")
    ap.add_argument("--tolerance", type=float, default=1e-6, help="a command differs beyond this (--resolve)")
    ap.add_argument("--json", type=Path, help="write the comparison (--resolve) or the run in simulate's format")
    ap.add_argument("--solver", help="--closed-loop: solver path (structural: a controller of its own)")
    ap.add_argument("--plant", choices=PLANT_INTEGRATIONS, help="--closed-loop: plant integration (default: the "
                    "plant the bag recorded; continuous: ZOH + DOP853, euler/rk4: one step per sample)")
    ap.add_argument("--timing", choices=("recorded", "ideal"), default="recorded",
                    help="--closed-loop, a real-time plant: the loop's timing as recorded (default) or ideal samples")
    ap.add_argument("--out", type=Path, help="--closed-loop: figures and metrics.json here")
    ap.add_argument("--sweep", help="--closed-loop: NAME=V1,V2,... of a run-time setting")
    args = ap.parse_args(argv)
    if args.closed_loop:
        return closed_loop_main(args)
    if args.sweep or args.out or args.solver or args.plant is not None or args.timing != "recorded":
        print("replay: error: --sweep, --out, --solver, --plant and --timing need --closed-loop", file=sys.stderr)
        return 2
    try:
        if not args.resolve:
            if not args.rate > 0:
                raise NmpcError(f"--rate must be positive, got {args.rate}")
            return republish(args.bag, args.rate, args.wait)
        overrides = {k: v for k, v in (("mu", args.mu), ("kappa", args.kappa)) if v is not None}
        inputs = replay_inputs(args.bag, args.config, overrides=overrides)
        run, settings = inputs.run, inputs.settings.replace(**overrides)
        report = resolve(run, settings, args.tolerance)
    except (BagError, NmpcError) as exc:
        print(f"replay: error: {exc}", file=sys.stderr)
        return 1
    for line in describe_inputs(inputs):
        print(f"replay --resolve: {line}")
    for s in report["steps"]:
        if s["max_abs_diff"] > args.tolerance:
            print(f"step {s['step']:4d}: recorded u {s['recorded_u']} resolved u {s['resolved_u']} "
                  f"(|du| {s['max_abs_diff']:.3g})")
    summary = report["summary"]
    print(f"replay --resolve: {summary['samples']} samples, {summary['steps_differing']} differ beyond "
          f"{args.tolerance:g}; max |du| {summary['max_abs_diff']:.3g}"
          + ("" if run.finished else " (the file was not finished)"))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report))
    return 0
