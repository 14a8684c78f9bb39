"""The recorder's parameter snapshots: each node that publishes a recorded topic is asked once for its
parameters (rcl_interfaces list_parameters, then get_parameters), without blocking the recorder.

The answer goes to a callback (the recorder writes it into the bag as an MCAP metadata record,
bag/node_parameters.py), so a bag says with which plant integration and controller settings it was
made. A node whose parameter services do not answer is asked again every `RETRY_PERIOD` s and given
up after `GIVE_UP_AFTER` s with one warning. A node whose parameter services never appear in the graph
is given up quietly (a debug line): it has none to ask; so is one that leaves the graph before they
appear. Short-lived publishers are such nodes: `send` (tools/send.py) creates its `send_<pid>` node
without parameter services, so it costs no warning.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from rcl_interfaces.srv import GetParameters, ListParameters
from rclpy.client import Client
from rclpy.node import Node
from rclpy.parameter import parameter_value_to_python
from rclpy.task import Future

#: node names of DDS participants that are not ROS nodes (no parameter services)
NOT_NODES = ("_NODE_NAME_UNKNOWN_", "_CREATED_BY_BARE_DDS_APP_")
#: s between two requests to a node that has not answered yet
RETRY_PERIOD = 1.0
#: s after a node was first seen: stop asking it
GIVE_UP_AFTER = 30.0


def node_names(endpoints: Iterable[Any]) -> set[str]:
    """Fully qualified names of the ROS nodes behind graph endpoints (rclpy TopicEndpointInfo)."""
    return {f"{e.node_namespace.rstrip('/')}/{e.node_name}" for e in endpoints if e.node_name not in NOT_NODES}


@dataclass
class _Pending:
    list_client: Client
    get_client: Client
    first_seen: float
    asked: float = -1e9
    #: the node's parameter names once listed
    names: list[str] | None = None
    #: what is asked and not answered: "list", "all" (every name at once) or one name each (see _answered)
    futures: dict[str, Future] = field(default_factory=dict)
    values: dict[str, Any] = field(default_factory=dict)
    one_by_one: bool = False
    #: its list_parameters service showed up in the graph (a node without one is given up quietly)
    has_services: bool = False


class ParameterSnapshots:
    """Snapshots of other nodes' parameters, taken once each; `poll(nodes)` from a timer, `destroy()` at the end.

    `on_snapshot(node, values, time_ns)`: called in the executor thread with the fully qualified node
    name, {parameter name: Python value (None = declared but unset)} and the node clock's time (ns).
    rclpy's get_parameters service answers nothing at all when one of the names is declared but
    unset (the controller has such parameters): then each name is asked on its own.
    """

    def __init__(self, node: Node, on_snapshot: Callable[[str, dict[str, Any], int], None]) -> None:
        self.node = node
        self.on_snapshot = on_snapshot
        self.pending: dict[str, _Pending] = {}
        #: the nodes whose parameters were taken (fully qualified name -> values)
        self.taken: dict[str, dict[str, Any]] = {}
        self.given_up: set[str] = set()

    def poll(self, nodes: set[str]) -> None:
        """Ask the new ones among `nodes` (fully qualified names), and again those that did not answer."""
        now = time.monotonic()
        for name in sorted(nodes - set(self.pending) - set(self.taken) - self.given_up):
            self.pending[name] = _Pending(self.node.create_client(ListParameters, f"{name}/list_parameters"),
                                          self.node.create_client(GetParameters, f"{name}/get_parameters"), now)
        for name, p in list(self.pending.items()):
            if name not in nodes and not p.has_services:  # gone before it offered any (send): nothing to ask
                self.node.get_logger().debug(f"no parameters of {name} in the bag: it left without parameter services")
                self._forget(name)
            elif now - p.first_seen > GIVE_UP_AFTER:
                log = self.node.get_logger()
                if p.has_services:
                    log.warning(f"no parameters of {name} in the bag: its parameter services did not answer in "
                                f"{GIVE_UP_AFTER:g} s")
                else:
                    log.debug(f"no parameters of {name} in the bag: it has no parameter services")
                self._forget(name)
                self.given_up.add(name)
            elif now - p.asked >= RETRY_PERIOD:
                self._ask(name, p, now)

    def _ask(self, name: str, p: _Pending, now: float) -> None:
        """(Re)send what is still unanswered; a request before the service is matched would be lost."""
        client = p.list_client if p.names is None else p.get_client
        if not client.service_is_ready():
            return
        p.has_services = True
        p.asked = now
        if p.names is None:
            requests = {"list": ListParameters.Request()}
        elif not p.one_by_one:
            requests = {"all": GetParameters.Request(names=p.names)}
        else:
            requests = {key: GetParameters.Request(names=[key]) for key in p.names if key not in p.values}
        for key, request in requests.items():
            future = client.call_async(request)
            p.futures[key] = future
            future.add_done_callback(lambda f, _name=name, _key=key: self._answered(_name, _key, f))

    def _answered(self, name: str, key: str, future: Future) -> None:
        p = self.pending.get(name)
        if p is None or p.futures.get(key) is not future or future.cancelled() or future.result() is None:
            return
        del p.futures[key]
        response = future.result()
        if key == "list":
            p.names = sorted(response.result.names)
        elif key == "all" and len(response.values) == len(p.names):
            p.values = {k: parameter_value_to_python(v) for k, v in zip(p.names, response.values)}
        elif key == "all":  # a name declared but unset spoils the whole answer: ask each on its own
            p.one_by_one = True
        else:  # one name: its value, or nothing when it is unset
            p.values[key] = parameter_value_to_python(response.values[0]) if response.values else None
        if p.names is not None and len(p.values) == len(p.names):
            self._forget(name)
            self.taken[name] = p.values
            self.on_snapshot(name, p.values, self.node.get_clock().now().nanoseconds)
        elif not p.futures:
            self._ask(name, p, time.monotonic())

    def _forget(self, name: str) -> None:
        p = self.pending.pop(name)
        for future in p.futures.values():
            future.cancel()
        self.node.destroy_client(p.list_client)
        self.node.destroy_client(p.get_client)

    def destroy(self) -> None:
        """Drop the requests still open (nothing waits for them)."""
        for name in list(self.pending):
            self._forget(name)
