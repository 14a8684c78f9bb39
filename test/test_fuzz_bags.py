"""Hostile input, fuzzed: MCAP files (bag.mcap_io).

Random bytes, truncations, bit flips and byte overwrites of valid bags written with
`Ros2McapWriter` (zstd and uncompressed, also with the chunk CRCs zeroed so that damaged chunk
contents reach the record parser and the CDR decoder) are read with `load_bag` and by iterating
`read_bag`. Proves: only BagError (with a message) ever comes out, nothing hangs, and whatever is
recovered is a prefix, per topic, of what was written; a truncated file is never reported finished.
"""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
from fuzzing import fuzz_settings, outcome, time_limit
from hypothesis import given
from hypothesis import strategies as st
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import Marker, MarkerArray

from nmpc_avoid_ros.bag.mcap_io import MAGIC, BagError, load_bag, read_bag
from nmpc_avoid_ros.bag.mcap_writer import Ros2McapWriter

CHUNK_OPCODE, DATA_END_OPCODE = 0x06, 0x0F


def _write(path: Path, compression: str) -> Path:
    with Ros2McapWriter(path, compression=compression, chunk_size=400) as bag:
        for i in range(24):
            bag.write_message("/state", Float64MultiArray(data=[float(i), -float(i)]), 1_000 * i)
            if i % 6 == 0:
                m = Marker(type=Marker.CYLINDER, id=i)
                m.scale.x = m.scale.y = 1.0
                bag.write_message("/obstacles", MarkerArray(markers=[m]), 1_000 * i + 1)
    return path


def _chunks_without_crc(data: bytes) -> tuple[bytes, list[tuple[int, int]]]:
    """The file with every chunk's uncompressed CRC set to 0 (= not checked), and the chunks' record spans."""
    out, pos, spans = bytearray(data), len(MAGIC), []
    while pos + 9 <= len(out):
        opcode, length = out[pos], struct.unpack_from("<Q", out, pos + 1)[0]
        body = pos + 9
        if opcode == CHUNK_OPCODE:
            struct.pack_into("<I", out, body + 24, 0)  # start, end, uncompressed size (3 x u64), then the crc
            spans.append((body + 28, body + length))
        if opcode == DATA_END_OPCODE:
            break
        pos = body + length
    assert spans, "the test bag has no chunks"
    return bytes(out), spans


@pytest.fixture(scope="module")
def originals(tmp_path_factory) -> dict[str, tuple[bytes, dict, list]]:
    """compression variant -> (file bytes, {topic: [(time, data)]} as written, chunk spans)."""
    out = {}
    for compression in ("zstd", "none"):
        path = _write(tmp_path_factory.mktemp("bags") / f"{compression}.mcap", compression)
        bag = load_bag(path)
        assert bag.finished and bag.counts() == {"/state": 24, "/obstacles": 4}
        data, spans = _chunks_without_crc(path.read_bytes())
        out[compression] = (path.read_bytes(), _summary(bag), [])
        out[f"{compression}-nocrc"] = (data, _summary(bag), spans)
    return out


def _summary(bag) -> dict[str, list]:
    def key(msg):
        return list(msg.data) if hasattr(msg, "data") else [m.id for m in msg.markers]
    return {topic: [(t, key(m)) for t, m in items] for topic, items in bag.topics.items()}


def _read_both_ways(path: Path) -> list:
    """load_bag and an iteration of read_bag (decoded and raw): results, or the BagError raised."""
    with time_limit(10.0):
        results = [outcome(lambda: load_bag(path), (BagError,))]
        reader = outcome(lambda: read_bag(path, decode=False), (BagError,))
        if not isinstance(reader, BaseException):
            results.append(outcome(lambda: [m.topic for m in reader], (BagError,)))
    return results


def _check_prefix(bag, written: dict[str, list]) -> None:
    got = _summary(bag)
    for topic, items in got.items():
        assert topic in written
        assert items == written[topic][: len(items)], f"{topic}: recovered messages are not what was written"


@fuzz_settings(60)
@given(st.binary(max_size=2000), st.booleans())
def test_random_bytes_raise_bag_error(tmp_path_factory, data: bytes, with_magic: bool) -> None:
    path = tmp_path_factory.mktemp("rand") / "random.mcap"
    path.write_bytes((MAGIC if with_magic else b"") + data)
    for result in _read_both_ways(path):
        if not isinstance(result, BaseException) and hasattr(result, "topics"):
            assert result.message_count == 0  # nothing can be recovered from noise


@fuzz_settings(60)
@given(st.sampled_from(["zstd", "none"]), st.data())
def test_truncated_bag_recovers_a_prefix_and_is_never_finished(tmp_path_factory, originals, compression: str,
                                                               data) -> None:
    raw, written, _ = originals[compression]
    cut = data.draw(st.integers(0, len(raw) - 1))
    path = tmp_path_factory.mktemp("cut") / "cut.mcap"
    path.write_bytes(raw[:cut])
    bag = _read_both_ways(path)[0]
    if not isinstance(bag, BaseException):
        assert not bag.finished
        _check_prefix(bag, written)


@fuzz_settings(120)
@given(st.sampled_from(["zstd", "none", "zstd-nocrc", "none-nocrc"]), st.data())
def test_damaged_bag_raises_bag_error_or_recovers(tmp_path_factory, originals, variant: str, data) -> None:
    raw, written, spans = originals[variant]
    buf = bytearray(raw)
    lo, hi = data.draw(st.sampled_from(spans)) if spans else (0, len(buf))
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(lo, hi - 1))
        if data.draw(st.booleans()):
            buf[i] ^= 1 << data.draw(st.integers(0, 7))
        else:
            buf[i] = data.draw(st.sampled_from([0x00, 0xFF, 0x7F, 0x80, data.draw(st.integers(0, 255))]))
    if data.draw(st.booleans()):
        buf = buf[: data.draw(st.integers(len(MAGIC), len(buf)))]
    path = tmp_path_factory.mktemp("dmg") / "damaged.mcap"
    path.write_bytes(bytes(buf))
    bag = _read_both_ways(path)[0]
    if not isinstance(bag, BaseException) and "nocrc" not in variant:
        _check_prefix(bag, written)  # with CRCs, a damaged chunk is never read as data
