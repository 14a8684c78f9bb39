"""The nodes' parameters as the recorder keeps them in a bag, and the run's set-up read back from them.

The recorder (nodes/recorder.py) asks every node that publishes a recorded topic for its parameters
once (rcl_interfaces list/get_parameters) and writes the answer as one MCAP metadata record:
name `PARAMETERS_RECORD`, keys `node` (fully qualified name), `parameters` (a JSON object:
parameter name -> value; unset ones left out) and `time_ns` (the recorder's clock when it got
them, ns). `recorded_setup` finds the controller's and the plant's among them, so that the offline
tools re-run a bag with the plant, integration and controller settings that produced it.

Runtime changes after the snapshot are not in it: mu and kappa are carried by every controller
sample (bag/analysis.RECORDED_PARAMETERS); the other runtime settings stay as they were when the
recorder asked.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

from ..core.config.settings import SETTINGS
from .mcap_io import Bag

#: the MCAP metadata record name of one node's parameter snapshot
PARAMETERS_RECORD = "ros2_node_parameters"


def parameters_record(node: str, values: dict[str, Any], time_ns: int) -> dict[str, str]:
    """The metadata record of one node's parameters (`values`: name -> Python value, None = unset, dropped)."""
    kept = {k: v for k, v in sorted(values.items()) if v is not None}
    return {"node": node, "parameters": json.dumps(kept), "time_ns": str(int(time_ns))}


def node_parameters(bag: Bag) -> tuple[dict[str, dict[str, Any]], list[str]]:
    """({fully qualified node name: its parameters}, notes on records that could not be read); a node
    recorded more than once (a split bag repeats the records) keeps its first snapshot."""
    nodes: dict[str, dict[str, Any]] = {}
    notes = []
    for name, data in bag.metadata:
        if name != PARAMETERS_RECORD:
            continue
        node = data.get("node", "")
        try:
            values = json.loads(data.get("parameters", ""))
        except ValueError as exc:
            notes.append(f"the parameters of {node or 'a node'} in the bag do not parse ({exc}); ignored")
            continue
        if not node or not isinstance(values, dict):
            notes.append("a parameter record without a node name or a JSON object; ignored")
            continue
        nodes.setdefault(node, values)
    return nodes, notes


def _namespace(node: str) -> str:
    return node.rsplit("/", 1)[0] or "/"


@dataclass
class RecordedSetup:
    """What the bag says about the controller and the plant that ran.

    `controller`: the controller node's core settings (the `controller` section of a params file,
    SETTINGS keys only) or None; `plant`: the plant node's parameters (model, integration,
    sample_time, lockstep, process_noise_std, ...) or None; `*_node`: whose they are; `notes`: one
    line each on what was missing or ambiguous.
    """

    controller: dict[str, Any] | None = None
    controller_node: str | None = None
    plant: dict[str, Any] | None = None
    plant_node: str | None = None
    notes: list[str] = field(default_factory=list)


def recorded_setup(bag: Bag, controller_node: str | None) -> RecordedSetup:
    """The controller's settings (from `controller_node`'s parameters, the name its diagnostics carry)
    and the plant's parameters (the node that declares `integration`, in the controller's namespace
    when there are several)."""
    nodes, notes = node_parameters(bag)
    setup = RecordedSetup(notes=notes)
    if not nodes:
        return setup
    if controller_node in nodes and "model" not in nodes[controller_node]:  # every controller declares it
        setup.notes.append(f"the parameters of {controller_node} in the bag lack its model (an incomplete "
                           "record); not used")
    elif controller_node in nodes:
        setup.controller_node = controller_node
        setup.controller = {k: v for k, v in nodes[controller_node].items() if k in SETTINGS}
    else:
        setup.notes.append(f"the bag holds parameters of {', '.join(sorted(nodes))} but not of the controller "
                           f"{controller_node or '(unnamed)'}")
    plants = sorted(n for n, values in nodes.items() if "integration" in values and "model" in values)
    if controller_node is not None and len(plants) > 1:
        plants = [n for n in plants if _namespace(n) == _namespace(controller_node)] or plants
    if len(plants) == 1:
        setup.plant_node, setup.plant = plants[0], nodes[plants[0]]
    elif plants:
        setup.notes.append(f"several plants in the bag ({', '.join(plants)}): none taken")
    return setup


def plant_sample_time(plant: dict[str, Any], default: float) -> float:
    """The plant's `sample_time` (s) when it is a finite positive number, else `default`."""
    value = plant.get("sample_time")
    return float(value) if isinstance(value, int | float) and math.isfinite(value) and value > 0 else default
