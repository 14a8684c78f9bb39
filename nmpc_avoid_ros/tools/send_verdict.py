"""What `send` (tools/send.py) learns from the controller: its model before the message goes out, and
its verdict on the message after.

Before: the controller's `model` and `sample_time` through its parameter service; a target whose size
is not the model's p is refused with exit 2 before it is published (`--no-check` skips this). A goal
takes the controller's `odom_frame` as its frame. While `send` waits for the controller's subscription,
a controller that subscribes `target` but not `goal_pose` is asked its `interface` once: `array` (it
will never subscribe `goal_pose`) ends `send goal` at once, naming the interface.
After: the controller's /diagnostics carry, per latched input, `<input>_received`, `<input>_verdict`
and `<input>_reason` (nodes/controller_inputs.py). `send` notes the count before it publishes and
waits until a diagnostics message of the controller counts one more: the verdict there is the one on
its message. A controller that publishes no diagnostics (inactive, or in lockstep without a plant:
it publishes them when it samples) gives no verdict: `send` says so and the message counts as
delivered. Two senders on one input at the same moment may each read the other's verdict.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..core.errors import NmpcError

#: inputs only one interface subscribes (nodes/controller.py): topic -> that interface
INTERFACE_INPUTS = {"goal_pose": "robot"}
#: frame of a goal when the controller has no `odom_frame` parameter (the controller's default)
DEFAULT_ODOM_FRAME = "odom"


class SendError(NmpcError):
    """Nothing to send to, no acknowledgement, or a refused parameter: the one line `send` prints."""


@dataclass(frozen=True)
class Verdict:
    """The controller's verdict on the message `send` published (`accepted` or `refused`)."""

    verdict: str
    reason: str
    received: int


class ControllerWatch:
    """Reads the controller `reader` (fully qualified): its model, and its verdicts on input `name`."""

    def __init__(self, node: Any, executor: Any, reader: str, name: str) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        from ..ros.parameters import STREAM_QOS

        self.node, self.executor, self.reader, self.name = node, executor, reader, name
        self.latest: dict[str, str] | None = None  # the last values of the controller's status
        self.sample_time = 1.0  # s, until read from the controller
        self.before: int | None = None  # the input's count before the publish (None: no diagnostics)
        self.interface: str | None = None  # the controller's `interface` once asked ("" if it did not say)
        self.subscription = node.create_subscription(DiagnosticArray, "/diagnostics", self._diagnostics, STREAM_QOS)

    def _diagnostics(self, msg: Any) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if status.hardware_id == self.reader and f"{self.name}_received" in values:
                self.latest = values

    def _spin(self, done: Callable[[], bool], timeout: float) -> bool:
        end = time.monotonic() + timeout
        while not done() and time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)
        return bool(done())

    def parameters(self, names: list[str], timeout: float) -> dict[str, Any]:
        """{name: value} of the controller's parameters; SendError (exit 1) if it does not answer."""
        from rclpy.parameter import parameter_value_to_python
        from rclpy.parameter_client import AsyncParameterClient

        client = AsyncParameterClient(self.node, self.reader)
        if not client.wait_for_services(timeout_sec=timeout):
            raise SendError(f"no parameter service of {self.reader} after {timeout:.1f} s to check the message "
                            f"against its model (--no-check sends unchecked)")
        future = client.get_parameters(names)
        if not self._spin(future.done, timeout):
            raise SendError(f"{self.reader} did not answer get_parameters in {timeout:.1f} s")
        values = future.result().values
        return {k: parameter_value_to_python(v) for k, v in zip(names, values)} if len(values) == len(names) else {}

    def check_target(self, values: list[float], timeout: float) -> None:
        """NmpcError (exit 2) if the controller's model takes another number of target values than `values`."""
        from ..core.errors import ConfigError
        from ..core.problem.models import make_model

        params = self.parameters(["model", "sample_time"], timeout)
        self.sample_time = float(params.get("sample_time") or self.sample_time)
        model = params.get("model")
        try:
            p = make_model(model).p
        except ConfigError:  # not this package's controller, or a model this process cannot build (its file)
            return
        if len(values) != p:
            raise NmpcError(f"target: {self.reader}'s model {model} takes {p} value{'s' * (p != 1)} (p = {p}), "
                            f"got {len(values)}: {' '.join(f'{v:g}' for v in values)}")

    def address_goal(self, msg: Any, frame: str | None, timeout: float) -> None:
        """Set the goal's header: `frame`, else the controller's `odom_frame` (else `odom`), and the stamp now."""
        try:
            params = self.parameters(["odom_frame", "sample_time"], timeout)
        except SendError:  # a reader without parameter services: the robot interface's default frame
            params = {}
        self.sample_time = float(params.get("sample_time") or self.sample_time)
        msg.header.frame_id = frame or str(params.get("odom_frame") or DEFAULT_ODOM_FRAME)
        msg.header.stamp = self.node.get_clock().now().to_msg()

    def absent(self, topic: str, timeout: float) -> str | None:
        """While the controller has no subscription on `topic` (resolved): why it never will (its
        `interface` has no such input), or None. Asked once, when the graph shows the controller's
        `target` subscription without one on `topic` (every interface subscribes `target`)."""
        needs = INTERFACE_INPUTS.get(self.name)
        if needs is None or self.interface is not None:
            return None
        namespace, _, short = self.reader.rpartition("/")
        try:
            subscribed = [t for t, _ in self.node.get_subscriber_names_and_types_by_node(short, namespace or "/")]
        except Exception:  # noqa: BLE001 - not in the graph (yet): rclpy raises NodeNameNonExistentError
            return None
        if topic in subscribed or not any(t.rsplit("/", 1)[-1] == "target" for t in subscribed):
            return None
        try:
            self.interface = str(self.parameters(["interface"], timeout).get("interface") or "")
        except NmpcError:  # no parameter services: wait for the subscription as before
            self.interface = ""
        if self.interface and self.interface != needs:
            return (f"{self.reader} has no {self.name} subscription: its interface is {self.interface!r}, and "
                    f"{self.name} is the {needs} interface's input (interface: {needs}); send it a target "
                    f"instead (send target ...)")
        return None

    def baseline(self, timeout: float) -> int | None:
        """The controller's count of messages on the input before `send` publishes (the diagnostics
        received so far, or the next within two samples and `timeout`); None if it publishes none."""
        self._spin(lambda: False, 0.1)  # take what is queued: the latest count counts
        self._spin(lambda: self.latest is not None, min(timeout, 2 * self.sample_time + 1.0))
        return None if self.latest is None else int(self.latest[f"{self.name}_received"])

    def prepare(self, args: Any, timeout: float, msg: Any = None) -> None:
        """Just before the publish: check a target against the model (unless --no-check), address a goal
        `msg`, and note the controller's count of the input's messages."""
        if args.what == "target" and not args.no_check:
            self.check_target(list(args.values), timeout)
        if args.what == "goal":
            self.address_goal(msg, args.frame, timeout)
        self.before = self.baseline(timeout)

    def verdict(self, before: int, timeout: float) -> Verdict | None:
        """The controller's verdict on the first message it counted after `before`; None if none in `timeout` s."""
        def counted() -> bool:
            return self.latest is not None and int(self.latest[f"{self.name}_received"]) > before

        if not self._spin(counted, timeout):
            return None
        values = self.latest
        return Verdict(values[f"{self.name}_verdict"], values.get(f"{self.name}_reason", ""),
                       int(values[f"{self.name}_received"]))

    def outcome(self, what: str, timeout: float) -> str:
        """After the publish: what to add to send's line ("; accepted by ..."), SendError if the controller
        refused it; no verdict to read: a line on stderr, and "" (delivered)."""
        found = None if self.before is None else self.verdict(self.before, timeout)
        if found is None:
            why = "publishes no diagnostics" if self.before is None else f"did not count it in {timeout:.1f} s"
            print(f"send: no verdict from {self.reader}: it {why} (inactive, or lockstep without a plant?); "
                  f"delivered, not confirmed", file=sys.stderr)
            return ""
        if found.verdict == "refused":
            raise SendError(f"{self.reader} refused {what}: {found.reason or 'no reason given'}")
        return f"; {found.verdict} by {self.reader}"
