"""Subscriptions for latched inputs (`target`, `obstacles`, `goal_pose`) that accept every publisher.

A user types `ros2 topic pub --once target ...`: that publisher is VOLATILE, and a TRANSIENT_LOCAL
subscription refuses it (DURABILITY mismatch; the publish then waits forever). A VOLATILE
subscription accepts both kinds, but a late-joining controller would miss the value a latched
publisher sent before it started.

Jazzy's `DurabilityPolicy.BEST_AVAILABLE` does not solve this: the subscription resolves its
durability once, when it is created, from the publishers discovered at that moment. Measured with
the Jazzy wheels (rmw_fastrtps): a controller started before any publisher resolves to
TRANSIENT_LOCAL and a later `ros2 topic pub` is refused exactly as before.

So `LatchedSubscription` holds two readers on the topic: a TRANSIENT_LOCAL one (late joiners get
the latched value) and a VOLATILE one (every publisher matches it). A sample of a transient-local
publisher reaches both; the second copy is recognised by its (source timestamp, publication
sequence number) and dropped before it is deserialised (a large MarkerArray costs its
deserialisation once), so the callback sees every sample once.

Order: both readers keep the last 10 samples and the latched one is created first, so within one
executor round it is served first. A burst from a transient-local publisher then sits in both
queues alike and is applied in order; with a latched reader of depth 1 the burst's last sample
overtook its first (measured: a velocity estimate from two quick marker updates went backwards).
A latched publisher with a history deeper than 1 that also publishes while the controller joins
could still interleave its history with the live samples; the package's publishers keep 1.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message

#: the accept-everything reader: keep 10 so a burst of incremental obstacle updates is not cut
VOLATILE_INPUT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                                durability=DurabilityPolicy.VOLATILE)
#: the late-joiner reader: transient local, and as deep as the volatile one (see "Order" above)
LATE_JOINER_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: samples remembered for the duplicate check (both copies of a sample arrive within a few spins)
_REMEMBERED = 64


class LatchedSubscription:
    """Two readers (transient local + volatile) on one topic; `callback(msg)` once per sample."""

    def __init__(self, node: Node, msg_type: Any, topic: str, callback: Callable[[Any], None]) -> None:
        self.node = node
        self.msg_type = msg_type
        self.callback = callback
        self._recent: deque[tuple[int, int]] = deque(maxlen=_REMEMBERED)
        # volatile publishers are refused by the latched reader by design; the volatile reader takes
        # them, so rclpy's default "incompatible QoS" warning would only mislead the user
        quiet = SubscriptionEventCallbacks(incompatible_qos=lambda _event: None)
        self.subscriptions = [
            node.create_subscription(msg_type, topic, self._receive, LATE_JOINER_QOS, event_callbacks=quiet,
                                     raw=True),
            node.create_subscription(msg_type, topic, self._receive, VOLATILE_INPUT_QOS, raw=True),
        ]

    def _receive(self, data: bytes, info: dict[str, Any]) -> None:
        stamp, sequence = info.get("source_timestamp"), info.get("publication_sequence_number")
        if stamp and sequence:  # rmws that report neither: no duplicate check (none is possible)
            key = (int(stamp), int(sequence))
            if key in self._recent:
                return
            self._recent.append(key)
        self.callback(deserialize_message(data, self.msg_type))

    def destroy(self) -> None:
        """Destroy both readers (lifecycle cleanup)."""
        for subscription in self.subscriptions:
            self.node.destroy_subscription(subscription)
        self.subscriptions = []
