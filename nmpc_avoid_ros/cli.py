"""Entry points of every executable; `python -m nmpc_avoid_ros <command>` dispatches to them.

Each entry imports its module lazily so that `--help` of one command never pays for the others
(rclpy, matplotlib, the CasADi build).
"""

from __future__ import annotations

import importlib
import sys

#: command -> (module, one-line description)
COMMANDS: dict[str, tuple[str, str]] = {
    "controller": ("nmpc_avoid_ros.nodes.controller", "ROS 2 node: the NMPC controller"),
    "plant": ("nmpc_avoid_ros.nodes.plant", "ROS 2 node: plant simulator (real time or lockstep)"),
    "recorder": ("nmpc_avoid_ros.nodes.recorder", "ROS 2 node: records topics into an MCAP bag (rosbag2 format)"),
    "obstacles": ("nmpc_avoid_ros.nodes.obstacles", "ROS 2 node: publishes a scene's moving obstacles as markers"),
    "analyze": ("nmpc_avoid_ros.tools.analyze", "bags -> metrics.json and figures, without a ROS graph"),
    "replay": ("nmpc_avoid_ros.tools.replay", "republish a bag, or re-solve the controller on it (--resolve)"),
    "simulate": ("nmpc_avoid_ros.tools.simulate", "offline closed loop of one configuration -> JSON"),
    "figures": ("nmpc_avoid_ros.tools.figures", "the paper's example offline -> figures + metrics"),
    "demo": ("nmpc_avoid_ros.tools.demo", "the paper's example through ROS 2 topics -> out/"),
    "bench": ("nmpc_avoid_ros.bench.main", "solver paths vs. Opti + IPOPT and do-mpc, one process -> JSON"),
    "campaign": ("nmpc_avoid_ros.evaluation.campaign.cli",
                 "Monte Carlo campaign over random scenarios (local or on Dask) -> JSON + plots"),
    "send": ("nmpc_avoid_ros.tools.send",
             "a target, a goal pose, an obstacle or a parameter to a running controller, acknowledged"),
}


def run(command: str, argv: list[str] | None = None) -> int:
    module = importlib.import_module(COMMANDS[command][0])
    return int(module.main(argv) or 0)


def _entry(command: str):
    def main() -> int:
        return run(command, sys.argv[1:])

    main.__name__ = f"{command}_main"
    return main


controller_main = _entry("controller")
plant_main = _entry("plant")
recorder_main = _entry("recorder")
obstacles_main = _entry("obstacles")
analyze_main = _entry("analyze")
replay_main = _entry("replay")
simulate_main = _entry("simulate")
figures_main = _entry("figures")
demo_main = _entry("demo")
bench_main = _entry("bench")
campaign_main = _entry("campaign")
send_main = _entry("send")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        width = max(map(len, COMMANDS))
        print("usage: python -m nmpc_avoid_ros <command> [args]\n\ncommands:")
        for name, (_, text) in COMMANDS.items():
            print(f"  {name:<{width}}  {text}")
        return 0 if argv else 2
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        print(f"unknown command {command!r}; commands: {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    return run(command, rest)
