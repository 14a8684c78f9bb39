"""`recorder`: writes the package's topics into an MCAP bag, as rosbag2 would (readable by ros2 bag, Foxglove).

    ros2 run nmpc_avoid_ros recorder --ros-args -p output:=bags/demo.mcap

Messages are taken as serialized CDR bytes (no deserialize / re-serialize) and written with the
node-clock receive time as log time (ns; sim time when use_sim_time) and the publisher's source
timestamp as publish time. Topic types come from the ROS graph: a timer polls it and subscribes
as soon as a wanted topic has a publisher (the `types` parameter, ``topic=pkg/msg/Type``, lets a
topic be subscribed before any publisher exists). QoS: `latched_topics` (target, goal_pose, obstacles)
reliable + transient local, depth 1, plus a volatile reader of depth `queue_depth` so that a volatile
publisher's first sample (`ros2 topic pub --once`, which the controller accepts at once) is not
lost before the graph poll sees that publisher; a sample both readers get is written once. The
others reliable, depth `queue_depth`; downgraded to volatile / best effort only when a publisher
offers that, so that every publisher matches.

`output`: a .mcap path, or a directory (then rosbag2 naming ``<dir>/<dir>_0.mcap``). With
`split_size` or `split_duration`, files are numbered ``<stem>_0.mcap``, ``<stem>_1.mcap``, ...
An unwritable path or a full disk is reported and ends the node with a non-zero exit status;
SIGINT / SIGTERM record what DDS received until SIGNAL_GRACE s after the signal (messages in flight
at the signal), finish the file and log the message count per topic, in well under a second
(publishers that go on publishing do not hold the exit up).

The nodes that publish a recorded topic are asked once for their parameters; each answer is an
MCAP metadata record (bag/node_parameters.py), so that `replay` reruns the bag with the plant
integration and the controller settings that made it. A node without parameter services (`send`) is
not asked and costs no warning (nodes/recorder_parameters.py).

While it records, `~/counts` (diagnostic_msgs/DiagnosticStatus, reliable, transient local) says
how many messages of each topic are written (a value per topic: key the topic, value the count),
every COUNTS_PERIOD s when they changed, and `parameters:<node>` = 1 for each node whose parameters
are in the bag. A tool that knows what a finished loop published waits
for those counts before it stops the nodes (tools/processes.settle): a message still on its way
when its publisher exits is lost.
"""

from __future__ import annotations

import importlib
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterType
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.subscription import Subscription

from ..bag.mcap_io import BagError
from ..bag.mcap_writer import COMPRESSIONS, DEFAULT_CHUNK_SIZE, Ros2McapWriter
from ..bag.node_parameters import PARAMETERS_RECORD, parameters_record
from ..core.errors import ConfigError
from ..ros.parameters import LATCHED_QOS, ParamSpec, declare
from .recorder_parameters import ParameterSnapshots, node_names
from .runner import run_node

#: the controller's interfaces (array: state, command, target; robot: odom, cmd_vel, goal_pose), obstacles, and
#: what the controller and the lockstep plant publish for the offline tools
DEFAULT_TOPICS = ["state", "command", "target", "odom", "cmd_vel", "goal_pose", "obstacles", "/diagnostics",
                  "controller/prediction", "controller/certificate", "/clock"]
#: the latched inputs (transient local publishers, as the controller subscribes them)
LATCHED_TOPICS = ["target", "goal_pose", "obstacles"]
#: messages taken per callback beyond the one the executor delivers (fairness between topics)
BATCH = 200
#: topics never recorded by `topics: ["*"]` (nor is the recorder's own ~/counts)
GRAPH_TOPICS = ("/rosout", "/parameter_events")
#: s between two `~/counts` messages at most (only sent when a count changed)
COUNTS_PERIOD = 0.1
#: s after SIGINT / SIGTERM whose messages are still recorded: those in flight at the signal arrive in it
SIGNAL_GRACE = 0.1
#: s the exit spends at most taking what the subscriptions hold (then the file is finished)
DRAIN_LIMIT = 0.5

RECORDER_SPECS = [
    ParamSpec("output", "", "the .mcap file or a directory; empty: bags/run-<YYYYmmdd-HHMMSS>.mcap",
              ParameterType.PARAMETER_STRING, read_only=True),
    ParamSpec("overwrite", False, "replace an existing output file instead of refusing to start",
              ParameterType.PARAMETER_BOOL, read_only=True),
    ParamSpec("topics", DEFAULT_TOPICS, "topics to record (relative names resolve in the node's namespace); "
              "[\"*\"]: every topic except /rosout, /parameter_events and its own ~/counts",
              ParameterType.PARAMETER_STRING_ARRAY, read_only=True),
    ParamSpec("types", None, "topic=pkg/msg/Type entries: subscribe before a publisher exists (the graph's type "
              "wins when they differ)", ParameterType.PARAMETER_STRING_ARRAY, read_only=True),
    ParamSpec("latched_topics", LATCHED_TOPICS, "topics subscribed transient local with depth 1 (plus a "
              "volatile reader, so volatile publishers are recorded from their first sample)",
              ParameterType.PARAMETER_STRING_ARRAY, read_only=True),
    ParamSpec("queue_depth", 1000, "subscription depth of the other topics, messages (a slow disk must lose "
              "nothing)", ParameterType.PARAMETER_INTEGER, read_only=True, int_range=(1, 1_000_000)),
    ParamSpec("compression", "zstd", "chunk compression", ParameterType.PARAMETER_STRING, read_only=True,
              choices=tuple(COMPRESSIONS)),
    ParamSpec("chunk_size", DEFAULT_CHUNK_SIZE, "uncompressed bytes per MCAP chunk", ParameterType.PARAMETER_INTEGER,
              read_only=True, int_range=(64, 2**31 - 1)),
    ParamSpec("flush_period", 5.0, "close the chunk being filled at least this often, s (bounds what a crash "
              "loses; 0 = only when full)", ParameterType.PARAMETER_DOUBLE, read_only=True,
              float_range=(0.0, 86400.0)),
    ParamSpec("split_size", 0, "start a new file after this many bytes; 0 = never", ParameterType.PARAMETER_INTEGER,
              read_only=True, int_range=(0, 2**62)),
    ParamSpec("split_duration", 0.0, "start a new file after this much log time, s; 0 = never",
              ParameterType.PARAMETER_DOUBLE, read_only=True, float_range=(0.0, 1e9)),
    ParamSpec("discovery_period", 0.25, "period of the graph poll that finds new topics, s",
              ParameterType.PARAMETER_DOUBLE, read_only=True, float_range=(0.01, 60.0)),
]


def output_paths(output: str, split: bool, now: datetime | None = None):
    """File name of the i-th file (i = 0, 1, ...) for the `output` parameter; see the module doc."""
    if not output:
        output = f"bags/run-{(now or datetime.now()).strftime('%Y%m%d-%H%M%S')}.mcap"
    path = Path(output).expanduser()
    if path.suffix == ".mcap":
        if not split:
            return lambda i: path
        return lambda i: path.with_name(f"{path.stem}_{i}.mcap")
    return lambda i: path / f"{path.name}_{i}.mcap"


def get_message(type_name: str) -> type:
    """The Python class of ``pkg/msg/Type`` (ImportError / AttributeError / ValueError when unknown)."""
    parts = type_name.split("/")
    if len(parts) != 3 or parts[1] != "msg":
        raise ValueError(f"not a message type name: {type_name!r}")
    return getattr(importlib.import_module(f"{parts[0]}.msg"), parts[2])


@dataclass
class _Topic:
    name: str
    type_name: str
    msg_class: type
    qos: QoSProfile
    subscription: Subscription | None = None
    # a latched topic subscribed transient local also has a volatile reader, so that a volatile
    # publisher's first sample (`ros2 topic pub --once`) is recorded before the graph poll sees it;
    # a sample both readers get is written once (recent keys: source timestamp, sequence number)
    companion: Subscription | None = None
    recent: deque = field(default_factory=lambda: deque(maxlen=64))
    count: int = 0
    publishers: int = 0
    last_sequence: int | None = None
    lost: int = 0
    warned: set[str] = field(default_factory=set)


class RecorderNode(Node):
    """Subscribes raw to the wanted topics and appends the bytes to a `Ros2McapWriter`."""

    def __init__(self, **kwargs) -> None:
        super().__init__("recorder", **kwargs)
        values = declare(self, RECORDER_SPECS)
        self.compression = str(values["compression"])
        if self.compression not in COMPRESSIONS:
            raise ConfigError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {self.compression!r}")
        self.chunk_size = int(values["chunk_size"])
        self.overwrite = bool(values["overwrite"])
        self.queue_depth = int(values["queue_depth"])
        self.split_size = int(values["split_size"])
        self.split_duration_ns = round(float(values["split_duration"]) * 1e9)
        wanted = list(values["topics"] or [])
        self.record_all = wanted == ["*"]
        self.wanted = [] if self.record_all else [self.resolve_topic_name(t) for t in wanted]
        self.latched = {self.resolve_topic_name(t) for t in values["latched_topics"] or []}
        self.type_hints: dict[str, str] = {}
        for entry in values["types"] or []:
            topic, sep, type_name = entry.partition("=")
            if not sep or not topic.strip() or type_name.count("/") != 2:
                raise ConfigError(f"types entries are topic=pkg/msg/Type, got {entry!r}")
            self.type_hints[self.resolve_topic_name(topic.strip())] = type_name.strip()

        self.path_of = output_paths(str(values["output"]), bool(self.split_size or self.split_duration_ns))
        self.files: list[Path] = []
        self.topics: dict[str, _Topic] = {}
        self.unrecordable: dict[str, str] = {}
        self.error: str | None = None
        self.file_start_ns: int | None = None
        #: system-clock ns of the SIGINT / SIGTERM (`signalled`): the exit records what DDS received until
        #: SIGNAL_GRACE s later
        self.stop_ns: int | None = None
        #: the parameter records written (each split file gets them all)
        self.parameter_records: list[dict[str, str]] = []
        self.writer: Ros2McapWriter = self._open_file()  # an unwritable output fails here, before any topic

        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.counts_topic = self.resolve_topic_name("~/counts")
        self.counts_pub = self.create_publisher(DiagnosticStatus, "~/counts", LATCHED_QOS)
        self.counts_sent: tuple[dict[str, int], str | None] | None = None
        self.counts_timer = self.create_timer(COUNTS_PERIOD, self.publish_counts, clock=steady)
        self.discovery_timer = self.create_timer(float(values["discovery_period"]), self.discover, clock=steady)
        flush_period = float(values["flush_period"])
        self.flush_timer = self.create_timer(flush_period, self.flush, clock=steady) if flush_period > 0 else None
        self.snapshots = ParameterSnapshots(self, self.keep_parameters)
        self.discover()
        self.get_logger().info(
            f"recording {'every topic' if self.record_all else ', '.join(self.wanted)} into {self.files[0]} "
            f"(compression {self.compression}, chunks of {self.chunk_size} B)")

    # ---- files

    def _open_file(self) -> Ros2McapWriter:
        path = self.path_of(len(self.files))
        writer = Ros2McapWriter(path, compression=self.compression, chunk_size=self.chunk_size,
                                overwrite=self.overwrite)
        self.files.append(path)
        self.file_start_ns = None
        for topic in self.topics.values():
            writer.add_topic(topic.name, topic.type_name)
        for record in self.parameter_records:
            writer.add_metadata(PARAMETERS_RECORD, record)
        return writer

    def _split_due(self, now_ns: int) -> bool:
        if self.split_size and self.writer.bytes_written >= self.split_size:
            return True
        return bool(self.split_duration_ns and self.file_start_ns is not None
                    and now_ns - self.file_start_ns >= self.split_duration_ns)

    def _next_file(self) -> None:
        self.writer.finish()
        self.get_logger().info(f"finished {self.files[-1]} ({self.writer.bytes_written} B); next file")
        self.writer = self._open_file()

    def fail(self, exc: Exception) -> None:
        """A write failed (full disk, I/O error): report it and end the node (non-zero exit)."""
        if self.error is None:
            self.error = str(exc)
            self.get_logger().error(f"recording stopped: {exc}")
            self.context.try_shutdown()  # ends run_node's spin loop; main() then exits with status 1

    # ---- topics

    def _qos_for(self, topic: str, current: QoSProfile | None = None) -> QoSProfile:
        """The package's QoS of a topic (docs/design.md, "Interfaces"), weakened where a publisher (or
        the `current` subscription) is weaker: best effort if any publisher is, volatile (with depth
        `queue_depth`) if any publisher is."""
        best_effort = current is not None and current.reliability == ReliabilityPolicy.BEST_EFFORT
        volatile = topic not in self.latched or (current is not None and
                                                 current.durability == DurabilityPolicy.VOLATILE)
        for info in self.get_publishers_info_by_topic(topic):
            best_effort |= info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
            volatile |= info.qos_profile.durability == DurabilityPolicy.VOLATILE
        return QoSProfile(
            depth=self.queue_depth if volatile else 1, history=HistoryPolicy.KEEP_LAST,
            reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE if volatile else DurabilityPolicy.TRANSIENT_LOCAL)

    def discover(self) -> None:
        """Subscribe to every wanted topic that now has a type (from the graph, else from `types`)."""
        if self.error is not None:
            return
        graph = dict(self.get_topic_names_and_types())
        names = [t for t in graph if t not in GRAPH_TOPICS and t != self.counts_topic] if self.record_all \
            else self.wanted
        for name in names:
            if name in self.unrecordable:
                continue
            types = graph.get(name, [])
            hint = self.type_hints.get(name)
            if not types and hint is None:
                continue
            type_name = types[0] if types else hint
            topic = self.topics.get(name)
            if topic is None:
                self._subscribe(name, type_name, types, hint)
            elif types:
                self._check(topic, types)
        publishers: set[str] = set()
        for topic in self.topics.values():
            infos = self.get_publishers_info_by_topic(topic.name)
            topic.publishers = len(infos)
            publishers |= node_names(infos)
        self.snapshots.poll(publishers - {self.get_fully_qualified_name()})

    def keep_parameters(self, node: str, values: dict, time_ns: int) -> None:
        """A node's parameters arrived (ParameterSnapshots): into the bag as a metadata record."""
        record = parameters_record(node, values, time_ns)
        self.parameter_records.append(record)
        if self.error is None:
            try:
                self.writer.add_metadata(PARAMETERS_RECORD, record)
            except BagError as exc:
                self.fail(exc)

    def _subscribe(self, name: str, type_name: str, types: list[str], hint: str | None) -> None:
        log = self.get_logger()
        if len(types) > 1:
            log.warning(f"{name} is published with several types {types}; recording {type_name}")
        if hint is not None and types and hint != type_name:
            log.warning(f"{name}: the graph says {type_name}, the types parameter {hint}; recording {type_name}")
        try:
            msg_class = get_message(type_name)
        except (AttributeError, ImportError, ValueError) as exc:
            self.unrecordable[name] = f"type {type_name} is not installed ({exc})"
            log.error(f"cannot record {name}: {self.unrecordable[name]}")
            return
        try:
            self.writer.add_topic(name, type_name)
        except BagError as exc:
            if self.writer.failed:
                self.fail(exc)
            else:  # e.g. no .msg definition for this type: skip the topic, loudly
                self.unrecordable[name] = str(exc)
                log.error(f"cannot record {name}: {exc}")
            return
        topic = _Topic(name, type_name, msg_class, self._qos_for(name))
        latched = topic.qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        # volatile writers are refused by the latched reader by design (the companion takes them)
        quiet = SubscriptionEventCallbacks(incompatible_qos=lambda _event: None) if latched else None
        topic.subscription = self.create_subscription(msg_class, name, self._callback(topic), topic.qos, raw=True,
                                                      event_callbacks=quiet)
        if latched:
            volatile = QoSProfile(depth=self.queue_depth, history=HistoryPolicy.KEEP_LAST,
                                  reliability=topic.qos.reliability, durability=DurabilityPolicy.VOLATILE)
            topic.companion = self.create_subscription(msg_class, name, self._callback(topic), volatile, raw=True)
        self.topics[name] = topic
        log.info(f"recording {name} [{type_name}] ({_describe(topic.qos)}"
                 f"{'; and volatile publishers' if topic.companion else ''})")

    def _check(self, topic: _Topic, types: list[str]) -> None:
        """A new publisher may need a weaker subscription to match (volatile, best effort): resubscribe."""
        if topic.type_name not in types and "type" not in topic.warned:
            topic.warned.add("type")
            self.get_logger().error(f"{topic.name} is now published as {types}, recorded as {topic.type_name}: "
                                    "those publishers are not recorded")
        qos = self._qos_for(topic.name, topic.qos)
        if qos.reliability != topic.qos.reliability or qos.durability != topic.qos.durability:
            self.take(topic, 1 << 30)  # keep what the old subscription already holds
            self.destroy_subscription(topic.subscription)
            if topic.companion is not None:  # the new subscription is volatile: it takes every writer
                self.take(topic, 1 << 30, topic.companion)
                self.destroy_subscription(topic.companion)
                topic.companion = None
            topic.qos = qos
            topic.subscription = self.create_subscription(topic.msg_class, topic.name, self._callback(topic), qos,
                                                          raw=True)
            self.get_logger().warning(f"{topic.name}: a publisher offers weaker QoS; now subscribed {_describe(qos)}")

    def _callback(self, topic: _Topic):
        def on_message(data: bytes, info: dict) -> None:
            self.record(topic, data, info)
            self.take(topic, BATCH)  # what else is queued, without one executor round per message

        return on_message

    def take(self, topic: _Topic, limit: int, sub: Subscription | None = None, until_ns: int | None = None) -> int:
        """Take up to `limit` queued messages of one topic straight from its subscription (or `sub`)
        and record them; with `until_ns`, stop after the first one DDS received later (system clock ns)."""
        sub = sub or topic.subscription
        taken = 0
        while sub is not None and taken < limit and self.error is None:
            with sub.handle:  # the executor's own way to take a message (rclpy Executor._take_subscription)
                item = sub.handle.take_message(sub.msg_type, True)
            if item is None:
                break
            self.record(topic, item[0], item[1])
            taken += 1
            if until_ns is not None and (item[1].get("received_timestamp") or 0) > until_ns:
                break
        return taken

    # ---- writing

    def record(self, topic: _Topic, data: bytes, info: dict) -> None:
        """Append one serialized message (log time = node clock now, ns); a copy already written (a
        latched topic's two readers) is dropped."""
        if self.error is not None:
            return
        key = (info.get("source_timestamp"), info.get("publication_sequence_number"))
        if topic.companion is not None and all(key):
            if key in topic.recent:
                return
            topic.recent.append(key)
        now = self.get_clock().now().nanoseconds
        try:
            if self._split_due(now):
                self._next_file()
            if self.file_start_ns is None:
                self.file_start_ns = now
            self.writer.write(topic.name, data, now, info.get("source_timestamp") or now,
                              info.get("publication_sequence_number") or 0)
        except BagError as exc:
            self.fail(exc)
            return
        topic.count += 1
        sequence = info.get("publication_sequence_number")
        if topic.publishers == 1 and sequence:  # one writer: its sequence numbers are consecutive
            if topic.last_sequence is not None and sequence > topic.last_sequence + 1:
                topic.lost += sequence - topic.last_sequence - 1
                self.get_logger().error(
                    f"{topic.name}: {topic.lost} messages lost so far (publisher sequence jumped from "
                    f"{topic.last_sequence} to {sequence}); the recorder falls behind or the QoS drops them",
                    throttle_duration_sec=2.0)
            elif topic.last_sequence is not None and sequence < topic.last_sequence:
                topic.publishers = -1  # a restarted or a second writer: unknown until the next graph poll
            topic.last_sequence = sequence
        else:
            topic.last_sequence = None

    def publish_counts(self) -> None:
        """`~/counts`: the messages written per topic (ERROR level, and the reason, once recording stopped)."""
        counts = {t.name: t.count for t in self.topics.values()}
        counts.update({f"parameters:{node}": 1 for node in self.snapshots.taken})
        if (counts, self.error) == self.counts_sent:
            return
        self.counts_sent = (counts, self.error)
        level, message = (DiagnosticStatus.ERROR, f"recording stopped: {self.error}") if self.error is not None \
            else (DiagnosticStatus.OK, f"{sum(counts.values())} messages written")
        self.counts_pub.publish(DiagnosticStatus(
            level=level, name=self.get_fully_qualified_name(), message=message,
            values=[KeyValue(key=name, value=str(n)) for name, n in counts.items()]))

    def flush(self) -> None:
        if self.error is None:
            try:
                self.writer.flush()
            except BagError as exc:
                self.fail(exc)

    def signalled(self) -> None:
        """In the SIGINT / SIGTERM handler: note the time (the exit records what DDS received until then
        and SIGNAL_GRACE s more)."""
        self.stop_ns = self.stop_ns or time.time_ns()

    def drain(self, before_ns: int | None = None, limit: float = DRAIN_LIMIT) -> int:
        """Take what DDS receives until `before_ns` (system clock ns; default now), waiting for that time
        if it is ahead: each reader up to its first later message, so publishers that go on do not
        keep it busy; at most `limit` s in all. Returns the messages taken."""
        before = time.time_ns() if before_ns is None else before_ns
        deadline = time.monotonic() + limit
        taken = 0
        while True:
            last_pass = time.time_ns() >= before
            for topic in list(self.topics.values()):
                for sub in (topic.subscription, topic.companion):
                    while sub is not None and self.error is None and time.monotonic() < deadline:
                        n = self.take(topic, BATCH, sub, until_ns=before)
                        taken += n
                        if n < BATCH:  # empty, or past `before`
                            break
            if last_pass or self.error is not None or time.monotonic() >= deadline:
                return taken
            time.sleep(min(0.01, max(0.0, (before - time.time_ns()) * 1e-9)))

    def close(self) -> None:
        """On SIGINT / SIGTERM: take what arrived until SIGNAL_GRACE s after the signal, finish the file,
        log the counts."""
        self.snapshots.destroy()
        stop = self.stop_ns if self.stop_ns is not None else time.time_ns()
        drained = self.drain(stop + round(SIGNAL_GRACE * 1e9)) if self.context.ok() else 0
        try:
            self.writer.finish()
        except BagError as exc:
            self.error = self.error or str(exc)
        log = self.get_logger()
        total = sum(t.count for t in self.topics.values())
        counts = ", ".join(f"{t.name} {t.count}" for t in self.topics.values()) or "no topic seen"
        missing = [t for t in self.wanted if t not in self.topics]
        verb = "received" if self.error is not None else "recorded"
        log.info(f"{verb} {total} messages into {', '.join(map(str, self.files))}"
                 f"{f' ({drained} drained at exit)' if drained else ''}: {counts}"
                 f"{'; never published: ' + ', '.join(missing) if missing else ''}")
        for topic in self.topics.values():
            if topic.lost:
                log.error(f"{topic.name}: {topic.lost} messages were published but never reached the recorder")
        for name, reason in self.unrecordable.items():
            log.error(f"not recorded: {name}: {reason}")
        if self.error is not None:
            log.error(f"the recording is incomplete: {self.error}")


def _describe(qos: QoSProfile) -> str:
    return (f"{'reliable' if qos.reliability == ReliabilityPolicy.RELIABLE else 'best effort'}, "
            f"{'transient local' if qos.durability == DurabilityPolicy.TRANSIENT_LOCAL else 'volatile'}, "
            f"depth {qos.depth}")


def main(argv: list[str] | None = None) -> int:
    """Run the recorder until SIGINT/SIGTERM; 0 when the bag is complete, 1 after a write error, 2 on bad config."""
    nodes: list[RecorderNode] = []

    def factory() -> RecorderNode:
        nodes.append(RecorderNode())
        return nodes[-1]

    status = run_node(factory, argv, "recorder", __doc__, on_stop=lambda node: node.close(),
                      on_signal=lambda node: node.signalled())
    if status == 0 and nodes and nodes[0].error is not None:
        print(f"recorder: error: {nodes[0].error}", file=sys.stderr)
        return 1
    return status


if __name__ == "__main__":
    sys.exit(main())
