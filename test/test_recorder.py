"""The MCAP writer/reader (nmpc_avoid_ros.bag.mcap_writer, .mcap_io) and the recorder node through real DDS.

Bags are read back with independent readers: `rosbags` (its own MCAP parser and .msg type system)
for finished files, the `mcap` library's stream reader for files cut short by kill -9.
"""

from __future__ import annotations

import os
import random
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk
from nav_msgs.msg import Path as PathMsg
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_types_from_msg
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import Marker, MarkerArray

from nmpc_avoid_ros.bag.mcap_io import BagError, load_bag, read_bag
from nmpc_avoid_ros.bag.mcap_writer import Ros2McapWriter
from nmpc_avoid_ros.bag.msg_definitions import SEPARATOR, field_dependencies, message_definition
from nmpc_avoid_ros.core.errors import NmpcError
from nmpc_avoid_ros.ros.parameters import LATCHED_QOS, STREAM_QOS
from nmpc_avoid_ros.tools.processes import NodeProcess, recorder_counts, settle

ROOT = Path(__file__).resolve().parents[1]
FLOATS = "std_msgs/msg/Float64MultiArray"


# ------------------------------------------------------------------------------------------------
# helpers


@pytest.fixture
def recorder(ros_graph, tmp_path):
    """start(*ros_args, preexec_fn=None) -> the recorder's NodeProcess in the test's domain; all stopped at the end."""
    _domain, env, _start, _probe = ros_graph
    started: list[NodeProcess] = []

    def start(*args: str, preexec_fn=None) -> NodeProcess:
        proc = NodeProcess("recorder", ["--ros-args", *args], env, tmp_path / "ros_logs", preexec_fn)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        if proc.alive():
            proc.stop(signal.SIGKILL)


def floats(*values: float) -> Float64MultiArray:
    return Float64MultiArray(data=[float(v) for v in values])


def wait_matched(probe, publishers, timeout: float = 30.0) -> None:
    assert probe.spin_until(lambda: all(p.get_subscription_count() >= 1 for p in publishers), timeout), \
        "the recorder never subscribed"


def tolerant_mcap_messages(path: Path) -> tuple[int, int]:
    """(messages, complete chunks) of a possibly unfinished file, read with the mcap library only."""
    messages = chunks = 0
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, emit_chunks=True).records:
                if isinstance(record, Chunk):
                    inner = breakup_chunk(record, validate_crc=True)  # a cut chunk fails here
                    chunks += 1
                    messages += sum(isinstance(r, Message) for r in inner)
        except Exception:  # the end of an unfinished file
            pass
    return messages, chunks


# ------------------------------------------------------------------------------------------------
# message definitions as rosbag2 stores them


def test_schema_text_is_the_msg_file_then_each_dependency_once():
    share = Path(sys.prefix) / "share" / "std_msgs" / "msg"
    text = message_definition(FLOATS)
    expected = (share / "Float64MultiArray.msg").read_text()
    for dep in ("MultiArrayLayout", "MultiArrayDimension"):
        expected += f"{SEPARATOR}\nMSG: std_msgs/{dep}\n" + (share / f"{dep}.msg").read_text()
    assert text == expected
    assert len(SEPARATOR) == 80 and set(SEPARATOR) == {"="}


def test_field_dependencies_handle_constants_defaults_arrays_and_header():
    text = """# a comment line with a Type word
int32 A=1
string<=10 NAME="x#y"   # bounded string constant
float64 x 0.5
int32[<=3] bounded
geometry_msgs/Point[] pts
Header header
other_pkg/msg/Thing t
Local[4] fixed
string<=5[<=2] names
builtin_interfaces/Time stamp
geometry_msgs/Point again
"""
    assert field_dependencies(text, "mypkg") == [
        "geometry_msgs/Point", "std_msgs/Header", "other_pkg/Thing", "mypkg/Local", "builtin_interfaces/Time"]


def test_definition_resolves_nested_types_recursively_once_each(tmp_path):
    msg = tmp_path / "share" / "pkg_a" / "msg"
    msg.mkdir(parents=True)
    (msg / "Top.msg").write_text("Mid mid\nLeaf[<=2] leaves\nuint8 K=3\nfloat64 v 1.5\n")
    (msg / "Mid.msg").write_text("Leaf leaf\nHeader header\n")
    (msg / "Leaf.msg").write_text("int32 a\n")
    std = tmp_path / "share" / "std_msgs" / "msg"
    std.mkdir(parents=True)
    (std / "Header.msg").write_text("string frame_id\n")
    text = message_definition("pkg_a/msg/Top", [tmp_path])
    assert [line for line in text.splitlines() if line.startswith("MSG: ")] == [
        "MSG: pkg_a/Mid", "MSG: pkg_a/Leaf", "MSG: std_msgs/Header"]
    types = get_types_from_msg(text, "pkg_a/msg/Top")  # an independent parser accepts it
    assert set(types) == {"pkg_a/msg/Top", "pkg_a/msg/Mid", "pkg_a/msg/Leaf", "std_msgs/msg/Header"}
    with pytest.raises(BagError, match="no definition Missing.msg"):
        message_definition("pkg_a/msg/Missing", [tmp_path])
    with pytest.raises(BagError, match="not a ROS message type name"):
        message_definition("nonsense", [tmp_path])


@pytest.mark.parametrize("cls", [Float64MultiArray, MarkerArray, DiagnosticArray, PathMsg, Clock])
def test_definitions_of_the_interface_types_parse_with_rosbags(cls):
    name = f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}"
    types = get_types_from_msg(message_definition(name), name)
    fields = [f[0] for f in types[name][1]]
    assert fields == list(cls.get_fields_and_field_types())


# ------------------------------------------------------------------------------------------------
# writer + reader without ROS graph


def write_sample(path: Path, n: int = 40, **kwargs) -> None:
    with Ros2McapWriter(path, **kwargs) as bag:
        for i in range(n):
            bag.write_message("/state", floats(i, -i), 1_000 + i)
            bag.write_message("/clock", Clock(clock=TimeMsg(sec=i, nanosec=7)), 1_000 + i)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_writer_round_trip_read_by_rosbags(tmp_path, compression):
    path = tmp_path / "a.mcap"
    write_sample(path, compression=compression, chunk_size=500)
    with AnyReader([path]) as reader:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        assert topics == {"/state": (FLOATS, 40), "/clock": ("rosgraph_msgs/msg/Clock", 40)}
        got = [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]
    states = [(t, list(m.data)) for topic, t, m in got if topic == "/state"]
    assert states == [(1_000 + i, [float(i), float(-i)]) for i in range(40)]
    bag = load_bag(path)
    assert bag.finished and bag.counts() == {"/state": 40, "/clock": 40} and bag.chunks > 3
    assert [m.clock.sec for _, m in bag.topics["/clock"]] == list(range(40))
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        f.seek(0)
        header = make_reader(f).get_header()
    assert header.profile == "ros2"
    assert {s.name: s.encoding for s in summary.schemas.values()} == {
        FLOATS: "ros2msg", "rosgraph_msgs/msg/Clock": "ros2msg"}
    assert all(c.message_encoding == "cdr" and c.metadata == {"offered_qos_profiles": ""}
               for c in summary.channels.values())
    expected = {"zstd": "zstd", "lz4": "lz4", "none": ""}[compression]
    assert {ci.compression for ci in summary.chunk_indexes} == {expected}


def test_writer_errors_are_bag_errors(tmp_path):
    path = tmp_path / "b.mcap"
    bag = Ros2McapWriter(path)
    bag.add_topic("/s", FLOATS)
    bag.write("/s", serialize_message(floats(1)), 5)
    with pytest.raises(BagError, match="was not added"):
        bag.write("/other", b"\x00", 5)
    with pytest.raises(BagError, match="already recorded as"):
        bag.add_topic("/s", "rosgraph_msgs/msg/Clock")
    bag.finish()
    bag.finish()  # safe twice
    with pytest.raises(BagError, match="already finished"):
        bag.write("/s", b"", 6)
    assert load_bag(path).counts() == {"/s": 1}
    with pytest.raises(BagError, match="refusing to overwrite"):
        Ros2McapWriter(path)
    with pytest.raises(BagError, match="compression must be one of"):
        Ros2McapWriter(tmp_path / "c.mcap", compression="bz2")
    with pytest.raises(BagError, match="cannot create .*forbidden"):
        Ros2McapWriter("/proc/forbidden/x.mcap")
    full = tmp_path / "full.mcap"
    full.symlink_to("/dev/full")
    with pytest.raises(BagError, match="No space left on device"):
        Ros2McapWriter(full, overwrite=True)


def test_reading_a_bag_loads_neither_rclpy_nor_message_packages(tmp_path):
    path = tmp_path / "a.mcap"
    write_sample(path)
    code = ("import sys\nfrom nmpc_avoid_ros.bag.mcap_io import load_bag\n"
            f"bag = load_bag({str(path)!r})\n"
            "print(bag.message_count, [m for m in sys.modules if m.split('.')[0] in "
            "('rclpy', 'std_msgs', 'rosgraph_msgs', 'casadi')])\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert out.stdout.split() == ["80", "[]"]


def test_broken_files_raise_bag_error_with_a_clear_reason(tmp_path):
    good = tmp_path / "good.mcap"
    write_sample(good)
    data = good.read_bytes()
    cases = {
        "text.mcap": (b"hello, this is a text file\n", "not an MCAP file"),
        "empty.mcap": (b"", "is empty"),
        "magic-cut.mcap": (data[:5], "truncated inside its MCAP header"),
        "header-cut.mcap": (data[:12], "truncated inside its MCAP header"),
        "header-cut2.mcap": (data[:20], "truncated inside its MCAP header"),
    }
    for name, (content, reason) in cases.items():
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(BagError, match=reason):
            load_bag(path)
        with pytest.raises(BagError, match=reason):
            read_bag(path)  # checked at once, before iterating
    with pytest.raises(BagError, match="does not exist"):
        load_bag(tmp_path / "missing.mcap")
    (tmp_path / "nothing").mkdir()
    with pytest.raises(BagError, match="without .mcap files"):
        load_bag(tmp_path / "nothing")


@pytest.mark.slow
def test_every_truncation_recovers_a_prefix_and_never_raises_another_error(tmp_path):
    good = tmp_path / "good.mcap"
    write_sample(good, n=60, chunk_size=300)
    data = good.read_bytes()
    full = load_bag(good)
    assert full.finished
    cut = tmp_path / "cut.mcap"
    previous = 0
    for size in range(0, len(data), 7):
        cut.write_bytes(data[:size])
        try:
            bag = load_bag(cut)
        except BagError as exc:
            assert "truncated inside its MCAP header" in str(exc) or "empty" in str(exc)
            continue
        assert not bag.finished
        states = [list(m.data) for _, m in bag.topics.get("/state", [])]
        assert states == [list(m.data) for _, m in full.topics["/state"][: len(states)]]
        assert bag.message_count >= previous  # more bytes never give fewer messages
        previous = bag.message_count
    assert previous >= full.message_count - 10  # only the last chunk (or summary) was missing


def test_random_damage_gives_bag_error_or_a_readable_bag(tmp_path):
    good = tmp_path / "good.mcap"
    write_sample(good, n=60, chunk_size=300)
    data = good.read_bytes()
    rng = random.Random(1)
    damaged = tmp_path / "damaged.mcap"
    for source in (data, data[: len(data) * 2 // 3]):
        for _ in range(200):
            buf = bytearray(source)
            for _ in range(rng.choice((1, 3))):
                buf[rng.randrange(len(buf))] = rng.randrange(256)
            damaged.write_bytes(bytes(buf))
            try:
                load_bag(damaged)
            except BagError:
                pass


# ------------------------------------------------------------------------------------------------
# the recorder node through DDS


@pytest.mark.slow
@pytest.mark.dds
def test_recorded_topics_read_back_with_rosbags(ros_graph, recorder, tmp_path):
    _domain, _env, _start, probe = ros_graph
    p = probe()
    target = p.node.create_publisher(Float64MultiArray, "target", LATCHED_QOS)
    obstacles = p.node.create_publisher(MarkerArray, "obstacles", LATCHED_QOS)
    target.publish(floats(5.0))  # before the recorder starts: transient local delivers it later
    marker = Marker(ns="box", id=3, type=Marker.CYLINDER, action=Marker.ADD)
    marker.header.frame_id = "state"
    marker.pose.position.x, marker.scale.x, marker.scale.y = 1.5, 2.0, 0.5
    obstacles.publish(MarkerArray(markers=[marker]))
    pubs = {
        "state": p.node.create_publisher(Float64MultiArray, "state", STREAM_QOS),
        "command": p.node.create_publisher(Float64MultiArray, "command", STREAM_QOS),
        "/diagnostics": p.node.create_publisher(DiagnosticArray, "/diagnostics", STREAM_QOS),
        "controller/prediction": p.node.create_publisher(PathMsg, "controller/prediction", STREAM_QOS),
        "/clock": p.node.create_publisher(Clock, "/clock", STREAM_QOS),
    }
    out = tmp_path / "bag" / "run.mcap"
    rec = recorder("-p", f"output:={out}")
    wait_matched(p, [target, obstacles, *pubs.values()])
    n = 30
    for i in range(n):
        pubs["state"].publish(floats(i, 0.5 * i))
        pubs["command"].publish(floats(-i))
        status = DiagnosticStatus(level=DiagnosticStatus.WARN, name="nmpc", message=f"step {i}",
                                  values=[KeyValue(key="solve_time", value=str(0.01 * i))])
        pubs["/diagnostics"].publish(DiagnosticArray(status=[status]))
        path = PathMsg()
        path.header.frame_id = "state"
        path.poses = [PoseStamped() for _ in range(3)]
        for j, pose in enumerate(path.poses):
            pose.pose.position.x, pose.pose.position.y = float(i + j), float(-j)
        pubs["controller/prediction"].publish(path)
        pubs["/clock"].publish(Clock(clock=TimeMsg(sec=i, nanosec=500_000_000)))
        p.spin_for(0.01)
    p.spin_for(0.5)
    assert rec.stop(signal.SIGINT) == 0, rec.output()
    assert "recorded 152 messages" in rec.output()

    expected = {
        "/state": (FLOATS, n), "/command": (FLOATS, n), "/target": (FLOATS, 1),
        "/obstacles": ("visualization_msgs/msg/MarkerArray", 1),
        "/diagnostics": ("diagnostic_msgs/msg/DiagnosticArray", n),
        "/controller/prediction": ("nav_msgs/msg/Path", n), "/clock": ("rosgraph_msgs/msg/Clock", n),
    }
    with AnyReader([out]) as reader:  # independent: rosbags' own MCAP and .msg parsers
        assert {c.topic: (c.msgtype, c.msgcount) for c in reader.connections} == expected
        got: dict[str, list] = {}
        for c, _t, raw in reader.messages():
            got.setdefault(c.topic, []).append(reader.deserialize(raw, c.msgtype))
    assert [list(m.data) for m in got["/state"]] == [[float(i), 0.5 * i] for i in range(n)]
    assert [list(m.data) for m in got["/command"]] == [[float(-i)] for i in range(n)]
    assert list(got["/target"][0].data) == [5.0]
    rec_marker = got["/obstacles"][0].markers[0]
    assert (rec_marker.ns, rec_marker.id, rec_marker.type, rec_marker.header.frame_id) == ("box", 3, 3, "state")
    assert (rec_marker.pose.position.x, rec_marker.scale.x, rec_marker.scale.y) == (1.5, 2.0, 0.5)
    assert [m.status[0].message for m in got["/diagnostics"]] == [f"step {i}" for i in range(n)]
    assert got["/diagnostics"][4].status[0].values[0].value == "0.04"
    assert [[(q.pose.position.x, q.pose.position.y) for q in m.poses] for m in got["/controller/prediction"]] == \
        [[(float(i + j), float(-j)) for j in range(3)] for i in range(n)]
    assert [(m.clock.sec, m.clock.nanosec) for m in got["/clock"]] == [(i, 500_000_000) for i in range(n)]

    bag = load_bag(out)  # the project's reader agrees
    assert bag.finished and bag.counts() == {t: c for t, (_, c) in expected.items()}
    assert [list(m.data) for _, m in bag.topics["/state"]] == [[float(i), 0.5 * i] for i in range(n)]
    times = [t for _, items in bag.topics.items() for t, _ in items]
    assert all(abs(t - time.time_ns()) < 120e9 for t in times)  # log time: receive time in ns


@pytest.mark.slow
@pytest.mark.dds
def test_publishers_with_weaker_qos_are_matched(ros_graph, recorder, tmp_path):
    """A volatile `target` publisher and a best-effort `state` publisher still reach the bag."""
    _domain, _env, _start, probe = ros_graph
    p = probe()
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    target = p.node.create_publisher(Float64MultiArray, "target", STREAM_QOS)
    state = p.node.create_publisher(Float64MultiArray, "state", best_effort)
    out = tmp_path / "weak.mcap"
    rec = recorder("-p", f"output:={out}")
    wait_matched(p, [target, state])
    for i in range(20):
        target.publish(floats(i))
        state.publish(floats(-i))
        p.spin_for(0.01)
    p.spin_for(0.5)
    assert rec.stop() == 0, rec.output()
    bag = load_bag(out)
    assert [m.data[0] for _, m in bag.topics["/target"]] == [float(i) for i in range(20)]
    assert len(bag.topics["/state"]) >= 18  # best effort on localhost: practically all
    assert "/target [std_msgs/msg/Float64MultiArray] (reliable, volatile, depth 1000)" in rec.output()
    assert "/state [std_msgs/msg/Float64MultiArray] (best effort, volatile, depth 1000)" in rec.output()


@pytest.mark.slow
@pytest.mark.dds
def test_kill_9_leaves_a_readable_file_with_the_completed_chunks(ros_graph, recorder, tmp_path):
    _domain, _env, _start, probe = ros_graph
    p = probe()
    pubs = [p.node.create_publisher(Float64MultiArray, name, STREAM_QOS) for name in ("state", "command")]
    out = tmp_path / "killed.mcap"
    chunk_size = 2048
    rec = recorder("-p", f"output:={out}", "-p", f"chunk_size:={chunk_size}", "-p", "flush_period:=0.0")
    wait_matched(p, pubs)
    sent = 0
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        for pub in pubs:
            pub.publish(floats(sent))
        sent += 1
        time.sleep(0.004)
    p.spin_for(0.5)  # let the recorder take everything: only the unfinished chunk may be lost
    assert rec.alive(), rec.output()
    assert rec.stop(signal.SIGKILL) == -signal.SIGKILL

    bag = load_bag(out)
    assert not bag.finished
    assert "not finished" in bag.describe()
    independent, chunks = tolerant_mcap_messages(out)
    assert bag.chunks == chunks >= 5 and bag.message_count == independent
    per_chunk = chunk_size // (31 + len(serialize_message(floats(sent))))  # messages that fit in one chunk
    assert bag.message_count >= 2 * sent - per_chunk - 1, (bag.message_count, 2 * sent, per_chunk)
    for topic in ("/state", "/command"):  # a gap-free prefix of what was published
        values = [m.data[0] for _, m in bag.topics[topic]]
        assert values == [float(i) for i in range(len(values))]
    print(f"kill -9 after {2 * sent} messages: {bag.chunks} chunks, {bag.message_count} messages recovered")


LOAD_SECONDS = 30.0
LOAD_RATE = 400.0  # per topic, Hz: 1.2 kHz in total on 3 topics


@pytest.mark.slow
@pytest.mark.dds
@pytest.mark.serial  # a throughput: alone on the machine
def test_load_1200_messages_per_second_for_30_s_loses_nothing(ros_graph, recorder, tmp_path):
    _domain, _env, _start, probe = ros_graph
    p = probe()
    pubs = [
        (p.node.create_publisher(Float64MultiArray, "state", STREAM_QOS), lambda k: floats(k, 0.5 * k)),
        (p.node.create_publisher(Float64MultiArray, "command", STREAM_QOS), lambda k: floats(-k)),
        (p.node.create_publisher(Clock, "/clock", STREAM_QOS),
         lambda k: Clock(clock=TimeMsg(sec=k // 1000, nanosec=(k % 1000) * 1_000_000))),
    ]
    out = tmp_path / "load.mcap"
    rec = recorder("-p", f"output:={out}")
    wait_matched(p, [pub for pub, _ in pubs])
    per_topic = int(LOAD_SECONDS * LOAD_RATE)
    sent = 0
    t0 = time.monotonic()
    while sent < per_topic:  # paced: publish what is due, then sleep until the next one
        due = min(per_topic, int((time.monotonic() - t0) * LOAD_RATE) + 1)
        while sent < due:
            for pub, make in pubs:
                pub.publish(make(sent))
            sent += 1
        time.sleep(max(0.0, t0 + sent / LOAD_RATE - time.monotonic()))
    elapsed = time.monotonic() - t0
    achieved = 3 * per_topic / elapsed
    p.spin_for(1.0)
    assert rec.stop(signal.SIGINT) == 0, rec.output()
    bag = load_bag(out)
    print(f"published {3 * per_topic} messages in {elapsed:.2f} s = {achieved:.0f} msg/s; "
          f"recorded {bag.message_count} in {bag.chunks} chunks, {out.stat().st_size} B")
    assert achieved >= 1000.0, f"the publisher reached only {achieved:.0f} msg/s"
    assert bag.finished and bag.counts() == {"/state": per_topic, "/command": per_topic, "/clock": per_topic}
    assert [m.data[0] for _, m in bag.topics["/command"]] == [float(-k) for k in range(per_topic)]
    assert [m.clock.nanosec for _, m in bag.topics["/clock"][:5]] == [0, 1_000_000, 2_000_000, 3_000_000, 4_000_000]


@pytest.mark.slow
@pytest.mark.dds
def test_split_by_size_writes_numbered_files_read_back_as_one_bag(ros_graph, recorder, tmp_path):
    _domain, _env, _start, probe = ros_graph
    p = probe()
    pub = p.node.create_publisher(Float64MultiArray, "state", STREAM_QOS)
    out = tmp_path / "split"
    rec = recorder("-p", f"output:={out}", "-p", "chunk_size:=1000", "-p", "split_size:=3000")
    wait_matched(p, [pub])
    for i in range(300):
        pub.publish(floats(*range(i, i + 8)))
        p.spin_for(0.002)
    p.spin_for(0.5)
    assert rec.stop(signal.SIGTERM) == 0, rec.output()
    files = sorted(out.glob("*.mcap"))
    assert len(files) >= 3 and files[0].name == "split_0.mcap"
    bag = load_bag(out)
    assert bag.finished and bag.counts() == {"/state": 300}
    assert [m.data[0] for _, m in bag.topics["/state"]] == [float(i) for i in range(300)]
    with AnyReader([files[1]]) as reader:  # each file stands alone
        assert [c.topic for c in reader.connections] == ["/state"]


@pytest.mark.dds
def test_unwritable_output_exits_non_zero_with_a_clear_message(ros_graph, recorder, tmp_path):
    rec = recorder("-p", "output:=/proc/forbidden/x.mcap")
    assert rec.proc.wait(30) != 0
    assert "cannot create /proc/forbidden/x.mcap" in rec.output()
    full = tmp_path / "full.mcap"
    full.symlink_to("/dev/full")
    rec = recorder("-p", f"output:={full}", "-p", "overwrite:=true")
    assert rec.proc.wait(30) != 0
    assert "No space left on device" in rec.output()
    rec = recorder("-p", f"output:={full}")  # an existing file is never overwritten silently
    assert rec.proc.wait(30) != 0
    assert "refusing to overwrite" in rec.output()


@pytest.mark.dds
def test_disk_full_while_recording_exits_non_zero_and_keeps_the_written_chunks(ros_graph, recorder, tmp_path):
    """RLIMIT_FSIZE makes a write fail with EFBIG mid-run, like a disk filling up."""
    _domain, _env, _start, probe = ros_graph
    p = probe()
    pub = p.node.create_publisher(Float64MultiArray, "state", STREAM_QOS)
    out = tmp_path / "full.mcap"
    limit = 60_000

    def limit_file_size() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    rec = recorder("-p", f"output:={out}", "-p", "chunk_size:=4000", "-p", "compression:=none",
                   preexec_fn=limit_file_size)
    wait_matched(p, [pub], timeout=60)
    i = 0
    while rec.alive() and i < 20_000:
        pub.publish(floats(*[i] * 10))
        i += 1
        time.sleep(0.001)
    assert rec.proc.wait(30) == 1, rec.output()
    assert "cannot write" in rec.output() and "File too large" in rec.output()
    bag = load_bag(out)
    assert not bag.finished and bag.chunks >= 5
    values = [m.data[0] for _, m in bag.topics["/state"]]
    assert values == [float(k) for k in range(len(values))]


@pytest.mark.slow
@pytest.mark.dds
def test_a_volatile_publisher_on_a_latched_topic_is_recorded_from_its_first_sample(ros_graph, recorder, tmp_path):
    """`ros2 topic pub --once target` (volatile) publishes as soon as any reader matches; the
    recorder's volatile companion reader records it at once; a latched sample is written once."""
    _domain, _env, _start, probe = ros_graph
    p = probe()
    latched = p.node.create_publisher(Float64MultiArray, "target", LATCHED_QOS)
    latched.publish(floats(1.0))
    out = tmp_path / "latched.mcap"
    rec = recorder("-p", f"output:={out}")
    assert p.spin_until(lambda: latched.get_subscription_count() >= 2, 30), rec.output()  # both readers
    # matched is not delivered: the history sample 1 goes out after discovery, and a reliable writer that
    # keeps 1 replaces a sample not yet acknowledged by the next one (sample 2 would supersede it)
    p.spin_for(1.0)
    latched.publish(floats(2.0))
    volatile = p.node.create_publisher(Float64MultiArray, "target", QoSProfile(depth=10))  # `ros2 topic pub`
    wait_matched(p, [volatile])
    volatile.publish(floats(3.0))  # at once, before any graph poll of the recorder
    p.spin_for(1.0)
    assert rec.stop() == 0, rec.output()
    values = [m.data[0] for _, m in load_bag(out).topics["/target"]]
    assert sorted(values) == [1.0, 2.0, 3.0], values
    assert "incompatible QoS" not in rec.output()


@pytest.mark.dds
def test_counts_say_what_is_written_so_a_publisher_may_exit_at_once_after_a_burst(ros_graph, recorder, tmp_path):
    """The recorder's ~/counts (not itself recorded, also with topics ["*"]) let tools/processes.settle
    wait until the last messages of a finished loop are in: the publisher exits right after, and the
    bag holds every message (a stop without that wait lost a lockstep demo's last 14 of 51 states)."""
    _domain, _env, _start, probe = ros_graph
    p = probe()
    pub = p.node.create_publisher(Float64MultiArray, "state", STREAM_QOS)
    recorded = recorder_counts(p.node)
    out = tmp_path / "burst.mcap"
    rec = recorder("-p", f"output:={out}", "-p", 'topics:=["*"]')
    wait_matched(p, [pub])
    n = 90  # one burst within the writer's history (STREAM depth 100): nothing is dropped before it is sent
    for i in range(n):
        pub.publish(floats(i))
    waited = settle(lambda: p.executor.spin_once(timeout_sec=0.02), {"/state": n}, recorded, timeout=30.0)
    assert recorded["/state"] == n
    p.node.destroy_publisher(pub)  # at once: what was not taken yet would be lost now
    assert rec.stop() == 0, rec.output()
    bag = load_bag(out)
    assert bag.finished and bag.counts() == {"/state": n}, bag.counts()  # no /recorder/counts in the bag
    assert [m.data[0] for _, m in bag.topics["/state"]] == [float(i) for i in range(n)]
    print(f"the recorder held the burst's {n} messages {waited * 1e3:.0f} ms after it was published")
    with pytest.raises(NmpcError, match=r"/state 90 of 91"):  # a message it never gets: a clear error
        settle(lambda: p.executor.spin_once(timeout_sec=0.02), {"/state": n + 1}, recorded, timeout=0.3)


def test_settle_spins_until_the_recorder_holds_what_was_heard_and_names_what_is_missing():
    recorded: dict[str, int] = {}

    def spin_once() -> None:  # the recorder's counts arrive one message at a time
        recorded["/state"] = recorded.get("/state", 0) + 1

    assert settle(spin_once, {"/state": 5}, recorded, timeout=10.0) < 10.0 and recorded == {"/state": 5}
    with pytest.raises(NmpcError, match=r"in 0.05 s: it holds /command 0 of 1$"):
        settle(lambda: None, {"/state": 5, "/command": 1}, recorded, timeout=0.05)


@pytest.mark.dds
def test_sigint_ends_the_recorder_within_a_second_while_publishers_go_on_and_loses_nothing(ros_graph, recorder,
                                                                                             tmp_path):
    """The exit took 4-7 s: it drained until the queues had been idle for 0.2 s, at most 5 s, and a
    plant publishing at 20 Hz never lets them idle. Now it records what DDS received until
    SIGNAL_GRACE s after the signal (what was in flight at it) and finishes the file."""
    _domain, _env, _start, probe = ros_graph
    p = probe()
    state = p.node.create_publisher(Float64MultiArray, "state", STREAM_QOS)
    clock = p.node.create_publisher(Clock, "/clock", STREAM_QOS)
    recorded = recorder_counts(p.node)
    out = tmp_path / "sigint.mcap"
    rec = recorder("-p", f"output:={out}")
    wait_matched(p, [state, clock])
    sent = 0

    def publish() -> None:
        nonlocal sent
        state.publish(floats(sent))
        clock.publish(Clock(clock=TimeMsg(sec=sent)))
        sent += 1

    rate = 50.0  # Hz per topic: faster than the plant's 20 Hz
    for _ in range(int(rate)):
        publish()
        p.spin_for(1.0 / rate)
    assert p.spin_until(lambda: recorded.get("/state", 0) > 0, 10.0), rec.output()
    for _ in range(80):  # a burst (within the writers' history, STREAM depth 100): queued as the signal comes
        publish()
    before = sent
    signalled = time.monotonic()
    rec.send(signal.SIGINT)
    while rec.alive() and time.monotonic() - signalled < 10.0:  # the publishers go on
        publish()
        time.sleep(1.0 / rate)
    exit_s = time.monotonic() - signalled
    assert rec.proc.wait(5) == 0, rec.output()
    print(f"the recorder exited {exit_s * 1e3:.0f} ms after SIGINT ({sent - before} messages per topic "
          "published meanwhile)")
    assert exit_s < 1.0, rec.output()
    bag = load_bag(out)
    assert bag.finished
    for topic, value in (("/state", lambda m: m.data[0]), ("/clock", lambda m: m.clock.sec)):
        values = [value(m) for _, m in bag.topics[topic]]
        # everything published before the signal (received within the grace on localhost), gap-free
        assert values == list(range(len(values))) and len(values) >= before, (topic, len(values), before)
    with AnyReader([out]) as reader:  # complete for an independent reader too
        assert {c.topic: c.msgcount for c in reader.connections} == bag.counts()


@pytest.mark.dds
def test_the_parameters_of_each_publishing_node_go_into_the_bag(ros_graph, recorder, tmp_path):
    from rclpy.parameter import Parameter

    from nmpc_avoid_ros.bag.node_parameters import node_parameters

    _domain, _env, _start, probe = ros_graph
    p = probe("plant_like")
    values = {"integration": "rk4", "sample_time": 0.25, "initial_state": [1.0, -2.0], "lockstep": True}
    p.node.declare_parameters("", [(k, v) for k, v in values.items()])
    p.node.declare_parameter("unset", Parameter.Type.STRING)  # declared, never set: left out
    pub = p.node.create_publisher(Float64MultiArray, "state", STREAM_QOS)
    quiet = probe("listener")  # publishes nothing recorded: not asked
    quiet.node.declare_parameter("secret", 1)
    recorded = recorder_counts(p.node)
    out = tmp_path / "split"
    rec = recorder("-p", f"output:={out}", "-p", "chunk_size:=1000", "-p", "split_size:=2000")
    wait_matched(p, [pub])
    assert p.spin_until(lambda: "parameters:/plant_like" in recorded, 30.0), (recorded, rec.output())
    for i in range(200):  # several split files: each holds the record
        pub.publish(floats(*range(i, i + 8)))
        p.spin_for(0.002)
        quiet.spin_for(0.0)
    p.spin_for(0.5)
    assert rec.stop() == 0, rec.output()
    files = sorted(out.glob("*.mcap"))
    assert len(files) >= 2
    for path in [out, *files]:
        nodes, notes = node_parameters(load_bag(path))
        assert notes == [] and set(nodes) == {"/plant_like"}, (path, nodes)
        assert nodes["/plant_like"] == {**values, "use_sim_time": False, "start_type_description_service": True}
