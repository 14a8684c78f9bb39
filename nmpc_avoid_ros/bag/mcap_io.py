"""MCAP bags as rosbag2 writes them, and a tolerant reader (no running ROS graph needed).

Writing (`Ros2McapWriter`) takes CDR bytes, e.g. straight from a `raw=True` subscription: profile
``ros2``, one schema per type (encoding ``ros2msg``: the type's .msg text, then every nested type
as a block introduced by a line of 80 ``=`` and ``MSG: pkg/Type``), channels with message encoding
``cdr`` and metadata ``offered_qos_profiles``, zstd-compressed chunks. Times are ns.

Reading (`read_bag`, `load_bag`) decodes with `mcap_ros2`. A file that was never finished (the
recorder was killed, the disk filled up) has no summary and no footer: it is read record by record
and every complete chunk is kept; the result says ``finished=False``. Anything that is not an MCAP
file, or is cut inside its header, raises `BagError` with a plain reason.
"""

from __future__ import annotations

import errno
import functools
import io
import os
import re
import struct
import sys
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Header, Message, Schema, Statistics
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from ..core.errors import NmpcError

MAGIC = b"\x89MCAP0\r\n"
#: rosbag2's default MCAP chunk size (the storage plugin's default), bytes
DEFAULT_CHUNK_SIZE = 768 * 1024
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
SEPARATOR = "=" * 80
BUILTIN_TYPES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
    "int64", "uint64", "string", "wstring",
})
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_ARRAY_SUFFIX = re.compile(r"\[[^\]]*\]$")


class BagError(NmpcError):
    """A bag cannot be written or read; the message names the file and the reason."""


# --------------------------------------------------------------------------------------------
# message definitions (.msg text with dependencies, as rosbag2 stores them)


def normalize_type(type_name: str) -> tuple[str, str]:
    """``pkg/msg/Type`` or ``pkg/Type`` -> (pkg, Type); BagError for anything else."""
    parts = type_name.strip().split("/")
    if len(parts) == 3 and parts[1] == "msg":
        parts = [parts[0], parts[2]]
    if len(parts) != 2 or not all(_NAME.match(p) for p in parts):
        raise BagError(f"not a ROS message type name: {type_name!r} (expected pkg/msg/Type)")
    return parts[0], parts[1]


def msg_search_paths() -> list[Path]:
    """Prefixes whose ``share/<pkg>/msg/<Type>.msg`` hold definitions: the venv, then AMENT_PREFIX_PATH."""
    prefixes = [Path(sys.prefix)]
    prefixes += [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    seen: list[Path] = []
    for p in prefixes:
        if p not in seen:
            seen.append(p)
    return seen


@functools.cache
def _msg_file_text(pkg: str, name: str, prefixes: tuple[Path, ...]) -> str:
    for prefix in prefixes:
        path = prefix / "share" / pkg / "msg" / f"{name}.msg"
        if path.is_file():
            return path.read_text(encoding="utf-8")
    where = ", ".join(str(p / "share" / pkg / "msg") for p in prefixes)
    raise BagError(f"no definition {name}.msg of {pkg}/msg/{name} under {where}")


def field_dependencies(text: str, pkg: str) -> list[str]:
    """Nested message types (``pkg/Type``) used by the fields of a .msg text, in order of appearance.

    Comments, blank lines, constants (``uint8 A=1``) and default values (``float64 x 0.5``) are
    handled; arrays (``T[]``, ``T[3]``, ``T[<=3]``) and bounded strings (``string<=10``) reduce to
    their element type; ``Header`` means ``std_msgs/Header``.
    """
    deps: list[str] = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        base = _ARRAY_SUFFIX.sub("", line.split()[0]).split("<=")[0]
        if base in BUILTIN_TYPES:
            continue
        if base == "Header":
            dep = "std_msgs/Header"
        elif "/" in base:
            dep = "/".join(normalize_type(base))
        elif _NAME.match(base):
            dep = f"{pkg}/{base}"
        else:
            raise BagError(f"cannot parse the field type {base!r} on line {number} of a {pkg} message: {raw!r}")
        if dep not in deps:
            deps.append(dep)
    return deps


def message_definition(type_name: str, prefixes: Iterable[Path] | None = None) -> str:
    """The full ``ros2msg`` schema text of a type, exactly as rosbag2 builds it.

    The type's own .msg text, then, depth first in order of first use, each nested type once:
    a line of 80 ``=``, a line ``MSG: pkg/Type`` and that type's .msg text.
    """
    prefixes = tuple(prefixes) if prefixes is not None else tuple(msg_search_paths())
    pkg, name = normalize_type(type_name)
    root = _msg_file_text(pkg, name, prefixes)
    parts = [root]
    seen = {f"{pkg}/{name}"}

    def append(dep: str) -> None:
        dep_pkg, dep_name = normalize_type(dep)
        text = _msg_file_text(dep_pkg, dep_name, prefixes)
        if not parts[-1].endswith("\n"):
            parts.append("\n")
        parts.append(f"{SEPARATOR}\nMSG: {dep}\n{text}")
        for sub in field_dependencies(text, dep_pkg):
            if sub not in seen:
                seen.add(sub)
                append(sub)

    for dep in field_dependencies(root, pkg):
        if dep not in seen:
            seen.add(dep)
            append(dep)
    return "".join(parts)


# --------------------------------------------------------------------------------------------
# writing


class _UnbufferedFile:
    """A write-only file with no user-space buffer: a completed chunk is in the kernel at once,
    so it survives a kill -9 of the writer. (Not an io.RawIOBase, which mcap would re-buffer.)"""

    def __init__(self, path: Path, overwrite: bool) -> None:
        flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
        self._fd: int | None = os.open(path, flags, 0o644)
        self._pos = 0

    def write(self, data: bytes) -> int:
        if self._fd is None:
            raise ValueError("write to a closed file")
        view = memoryview(data)
        while view:
            written = os.write(self._fd, view)
            if written <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            view = view[written:]
            self._pos += written
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)


class Ros2McapWriter:
    """Writes CDR-serialized ROS 2 messages into one MCAP file the way rosbag2 does.

    Use as a context manager (the file is finished on exit, also after an exception)::

        with Ros2McapWriter("run.mcap") as bag:
            bag.add_topic("/state", "std_msgs/msg/Float64MultiArray")
            bag.write("/state", cdr_bytes, log_time_ns)

    `path`: the .mcap file (parent directories are created; an existing file is an error unless
    `overwrite`). `compression`: ``zstd`` (default), ``lz4`` or ``none``, per chunk. `chunk_size`:
    uncompressed bytes per chunk. Every OS error (unwritable path, full disk) becomes a `BagError`.
    """

    def __init__(self, path: str | os.PathLike, *, compression: str = "zstd", chunk_size: int = DEFAULT_CHUNK_SIZE,
                 overwrite: bool = False, msg_prefixes: Iterable[Path] | None = None) -> None:
        self.path = Path(path)
        if compression not in COMPRESSIONS:
            raise BagError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
        if int(chunk_size) < 1:
            raise BagError(f"chunk_size must be a positive number of bytes, got {chunk_size}")
        self.compression = compression
        self.chunk_size = int(chunk_size)
        self._prefixes = tuple(msg_prefixes) if msg_prefixes is not None else tuple(msg_search_paths())
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.types: dict[str, str] = {}
        #: messages written per topic
        self.counts: Counter[str] = Counter()
        self._finished = False
        self._failed: BagError | None = None
        self._file: _UnbufferedFile | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise BagError(f"cannot create {self.path}: cannot create its directory {self.path.parent}: "
                           f"{exc.strerror or exc}") from None
        try:
            self._file = _UnbufferedFile(self.path, overwrite)
        except FileExistsError:
            raise BagError(f"cannot create {self.path}: the file exists (refusing to overwrite it)") from None
        except OSError as exc:
            raise BagError(f"cannot create {self.path}: {exc.strerror or exc}") from None
        self._writer = Writer(self._file, chunk_size=self.chunk_size, compression=COMPRESSIONS[compression])
        self._guard(lambda: self._writer.start(profile="ros2", library=f"nmpc_avoid_ros {LIBRARY_IDENTIFIER}"))

    def __enter__(self) -> Ros2McapWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.finish()
        else:  # keep what was written, but do not hide the original exception
            try:
                self.finish()
            except BagError:
                pass

    def _guard(self, action):
        if self._failed is not None:
            raise self._failed
        if self._finished:
            raise BagError(f"{self.path} is already finished")
        try:
            return action()
        except OSError as exc:
            self._failed = BagError(f"cannot write {self.path}: {exc.strerror or exc}")
            raise self._failed from None

    @property
    def finished(self) -> bool:
        return self._finished

    @property
    def failed(self) -> bool:
        """True after an OS error (full disk, I/O error): the file cannot be written any more."""
        return self._failed is not None

    @property
    def bytes_written(self) -> int:
        """Bytes in the file so far (the chunk being filled is not counted until it is written)."""
        return self._file.tell() if self._file is not None else 0

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def add_topic(self, topic: str, type_name: str, *, metadata: dict[str, str] | None = None) -> int:
        """Register a channel (and its type's schema once); returns the channel id. Idempotent."""
        if topic in self._channels:
            if self.types[topic] != type_name:
                raise BagError(f"topic {topic} is already recorded as {self.types[topic]}, not {type_name}")
            return self._channels[topic]
        pkg, name = normalize_type(type_name)
        full_name = f"{pkg}/msg/{name}"
        if full_name not in self._schemas:
            text = message_definition(full_name, self._prefixes)
            self._schemas[full_name] = self._guard(
                lambda: self._writer.register_schema(full_name, "ros2msg", text.encode()))
        meta = {"offered_qos_profiles": ""} if metadata is None else dict(metadata)
        schema_id = self._schemas[full_name]
        channel_id = self._guard(lambda: self._writer.register_channel(topic, "cdr", schema_id, meta))
        self._channels[topic] = channel_id
        self.types[topic] = type_name
        return channel_id

    def write(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None,
              sequence: int = 0) -> None:
        """Append one CDR-serialized message; `log_time_ns` (receive time) and `publish_time_ns` in ns."""
        channel_id = self._channels.get(topic)
        if channel_id is None:
            raise BagError(f"topic {topic} was not added to {self.path} (call add_topic first)")
        publish = log_time_ns if publish_time_ns is None else publish_time_ns
        self._guard(lambda: self._writer.add_message(channel_id, int(log_time_ns), bytes(data), int(publish),
                                                     int(sequence) & 0xFFFFFFFF))
        self.counts[topic] += 1

    def write_message(self, topic: str, msg: Any, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Serialize an rclpy message object with rclpy and append it (adds the topic if needed)."""
        from rclpy.serialization import serialize_message  # only this convenience needs rclpy

        module = type(msg).__module__.split(".")
        type_name = f"{module[0]}/msg/{type(msg).__name__}"
        if topic not in self._channels:
            self.add_topic(topic, type_name)
        self.write(topic, serialize_message(msg), log_time_ns, publish_time_ns)

    def flush(self) -> None:
        """Close the chunk being filled and hand it to the kernel (it then survives a crash)."""
        self._guard(self._writer.flush)

    def finish(self) -> None:
        """Write the last chunk, the summary and the footer, and close the file. Safe to call twice."""
        if self._finished:
            return
        try:
            if self._failed is None:
                self._guard(self._writer.finish)
        finally:
            self._finished = True
            if self._file is not None:
                self._file.close()


# --------------------------------------------------------------------------------------------
# reading


@dataclass
class BagMessage:
    """One recorded message: times in ns; `message` is decoded (attribute access) or raw CDR bytes."""

    topic: str
    type_name: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    message: Any


@dataclass
class FileReport:
    """What reading one .mcap file found. `finished`: it has its footer (the writer closed it)."""

    path: Path
    size: int
    finished: bool
    chunks: int = 0
    bad_chunks: int = 0
    messages: int = 0
    warnings: list[str] = field(default_factory=list)


class _Truncated(Exception):
    pass


class _StrictFile:
    """A read-only stream that raises `_Truncated` on a short read (mcap's reader would silently
    accept a partial chunk at the end of an unfinished file)."""

    def __init__(self, raw: io.BufferedReader) -> None:
        self._raw = raw

    def read(self, n: int = -1) -> bytes:
        data = self._raw.read(n)
        if n is not None and n >= 0 and len(data) < n:
            raise _Truncated()
        return data

    def tell(self) -> int:
        return self._raw.tell()


def _bag_files(path: Path) -> list[Path]:
    if path.is_dir():
        files = sorted(path.glob("*.mcap"), key=lambda p: [int(t) if t.isdigit() else t
                                                             for t in re.split(r"(\d+)", p.name)])
        if not files:
            raise BagError(f"{path} is a directory without .mcap files")
        return files
    if not path.exists():
        raise BagError(f"{path} does not exist")
    return [path]


def _check_file(path: Path) -> FileReport:
    """Magic, a complete Header record and the footer: BagError unless it is (a start of) an MCAP."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(8 + 9)
            if size == 0:
                raise BagError(f"{path} is empty (0 bytes): not an MCAP bag")
            if not MAGIC.startswith(head[:8]):
                raise BagError(f"{path} is not an MCAP file (it starts with {head[:8]!r}, not the MCAP magic)")
            if len(head) < 17:
                raise BagError(f"{path} is truncated inside its MCAP header ({size} bytes): it holds no data")
            opcode, length = head[8], struct.unpack("<Q", head[9:17])[0]
            if opcode != Opcode.HEADER:
                raise BagError(f"{path} is corrupt: the MCAP magic is not followed by a header record")
            if 17 + length > size:
                raise BagError(f"{path} is truncated inside its MCAP header ({size} bytes): it holds no data")
            finished = False
            if size >= 17 + length + 9 + 20 + 8:
                f.seek(-(9 + 20 + 8), os.SEEK_END)
                tail = f.read()
                finished = tail.endswith(MAGIC) and tail[0] == Opcode.FOOTER and tail[1:9] == struct.pack("<Q", 20)
    except OSError as exc:
        raise BagError(f"cannot read {path}: {exc.strerror or exc}") from None
    return FileReport(path=path, size=size, finished=finished)


class BagReader:
    """Iterates the messages of a bag (a .mcap file, or a directory of numbered .mcap files) in file
    order. The files are checked when the reader is made (BagError at once for a non-MCAP file);
    `finished` is known then, the per-file `reports` (chunks kept, damaged chunks) after iterating.
    """

    def __init__(self, path: str | os.PathLike, topics: Iterable[str] | None = None, *, decode: bool = True) -> None:
        self.path = Path(path)
        self.topics = None if topics is None else set(topics)
        self.decode = decode
        self.reports = [_check_file(p) for p in _bag_files(self.path)]
        self.types: dict[str, str] = {}

    @property
    def finished(self) -> bool:
        """True when every file has its footer, i.e. the writer finished it."""
        return all(r.finished for r in self.reports)

    def __iter__(self) -> Iterator[BagMessage]:
        for report in self.reports:
            yield from self._read_file(report)

    def _read_file(self, report: FileReport) -> Iterator[BagMessage]:
        from mcap_ros2.decoder import DecoderFactory  # lazily: `finished` checks need no decoder

        factory = DecoderFactory()
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        decoders: dict[int, Any] = {}
        statistics: Statistics | None = None
        seen: Counter[int] = Counter()
        path = report.path
        report.chunks = report.bad_chunks = report.messages = 0  # a second pass counts afresh
        report.warnings.clear()

        def emit(record: Message) -> BagMessage | None:
            channel = channels.get(record.channel_id)
            if channel is None:
                raise BagError(f"{path} is corrupt: a message refers to channel {record.channel_id}, never defined")
            seen[channel.id] += 1
            report.messages += 1
            if self.topics is not None and channel.topic not in self.topics:
                return None
            schema = schemas.get(channel.schema_id)
            type_name = schema.name if schema is not None else ""
            payload: Any = record.data
            if self.decode:
                decoder = decoders.get(channel.id)
                if decoder is None:
                    try:
                        decoder = factory.decoder_for(channel.message_encoding, schema)
                    except Exception as exc:  # the schema text of a foreign file may not parse
                        raise BagError(f"{path}: cannot decode topic {channel.topic} ({type_name}): {exc}") from None
                    if decoder is None:
                        raise BagError(f"{path}: topic {channel.topic} has message encoding "
                                       f"{channel.message_encoding!r} / schema encoding "
                                       f"{schema.encoding if schema else 'none'!r}; only cdr + ros2msg decode "
                                       f"(read with decode=False for raw bytes)")
                    decoders[channel.id] = decoder
                try:
                    payload = decoder(record.data)
                except Exception as exc:
                    raise BagError(f"{path}: a message on {channel.topic} does not decode as {type_name}: {exc}") \
                        from None
            return BagMessage(channel.topic, type_name, record.log_time, record.publish_time, record.sequence, payload)

        def handle(record: Any) -> BagMessage | None:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
                schema = schemas.get(record.schema_id)
                if schema is not None:
                    self.types.setdefault(record.topic, schema.name)
            elif isinstance(record, Message):
                return emit(record)
            return None

        try:
            raw = open(path, "rb")  # noqa: SIM115 - closed in finally (a generator)
        except OSError as exc:
            raise BagError(f"cannot read {path}: {exc.strerror or exc}") from None
        try:
            reader = StreamReader(_StrictFile(raw), emit_chunks=True, record_size_limit=max(report.size, 1))
            records = reader.records
            while True:
                offset = raw.tell()
                try:
                    record = next(records)
                except StopIteration:
                    break
                except Exception as exc:  # truncation, or a damaged record (any parse error of the mcap reader)
                    if report.finished:
                        raise BagError(f"{path} is corrupt at byte {offset}: {_reason(exc)}") from None
                    if offset >= report.size:
                        break
                    report.warnings.append(f"the file was not finished: {report.size - offset} bytes at its end "
                                           f"(from byte {offset}) are an incomplete record and were dropped")
                    break
                if isinstance(record, Chunk):
                    try:
                        inner = breakup_chunk(record, validate_crc=True)
                    except Exception as exc:  # bad compression / crc / framing inside one chunk
                        if report.finished:
                            raise BagError(f"{path} is corrupt: the chunk at byte {offset} is damaged "
                                           f"({_reason(exc)})") from None
                        report.bad_chunks += 1
                        report.warnings.append(f"skipped a damaged chunk at byte {offset}: {_reason(exc)}")
                        continue
                    report.chunks += 1
                    for item in inner:
                        out = handle(item)
                        if out is not None:
                            yield out
                elif isinstance(record, Statistics):
                    statistics = record
                elif isinstance(record, Footer | Header):
                    continue
                else:
                    out = handle(record)
                    if out is not None:
                        yield out
        finally:
            raw.close()
        if statistics is not None:
            for channel_id, count in statistics.channel_message_counts.items():
                if seen[channel_id] != count:
                    topic = channels[channel_id].topic if channel_id in channels else f"channel {channel_id}"
                    raise BagError(f"{path} is corrupt: its summary counts {count} messages on {topic}, "
                                   f"the chunks hold {seen[channel_id]}")
        for channel in channels.values():
            schema = schemas.get(channel.schema_id)
            self.types.setdefault(channel.topic, schema.name if schema else "")


def _reason(exc: BaseException) -> str:
    if isinstance(exc, _Truncated):
        return "unexpected end of file"
    return str(exc) or type(exc).__name__


def read_bag(path: str | os.PathLike, topics: Iterable[str] | None = None, *, decode: bool = True) -> BagReader:
    """Messages of a bag, lazily, in file order: iterate the returned `BagReader` (see its `finished`).

    `path`: a .mcap file or a directory of .mcap files (split recordings, read in numeric order).
    `topics`: only these (fully qualified names); `decode=False` gives the raw CDR bytes.
    """
    return BagReader(path, topics, decode=decode)


@dataclass
class Bag:
    """A bag in memory: per topic, the (log_time_ns, message) pairs sorted by log time."""

    path: Path
    topics: dict[str, list[tuple[int, Any]]]
    types: dict[str, str]
    finished: bool
    files: list[FileReport]

    @property
    def message_count(self) -> int:
        return sum(len(v) for v in self.topics.values())

    @property
    def chunks(self) -> int:
        """Complete chunks read (after a crash: the chunks that were recovered)."""
        return sum(r.chunks for r in self.files)

    @property
    def warnings(self) -> list[str]:
        return [f"{r.path.name}: {w}" for r in self.files for w in r.warnings]

    def counts(self) -> dict[str, int]:
        """Messages per topic."""
        return {t: len(v) for t, v in self.topics.items()}

    def describe(self) -> str:
        """One line for tools: file, counts, and whether the file was finished."""
        state = "finished" if self.finished else "the file was not finished (recovered the complete chunks)"
        counts = ", ".join(f"{t} {n}" for t, n in sorted(self.counts().items()))
        return f"{self.path}: {self.message_count} messages in {self.chunks} chunks, {state}; {counts}"


def load_bag(path: str | os.PathLike, topics: Iterable[str] | None = None, *, decode: bool = True,
             progress_every: int = 0) -> Bag:
    """Read a whole bag: every topic (also those without messages) -> [(log_time_ns, msg)], sorted by time.

    A bag that was not finished is recovered up to its last complete chunk (`finished` False).
    With `progress_every` > 0, a line goes to stderr every that many messages (long bags).
    Raises BagError for anything that is not a readable MCAP bag.
    """
    reader = read_bag(path, topics, decode=decode)
    per_topic: dict[str, list[tuple[int, Any]]] = {}
    for i, m in enumerate(reader, 1):
        per_topic.setdefault(m.topic, []).append((m.log_time_ns, m.message))
        if progress_every and i % progress_every == 0:
            print(f"  {Path(path).name}: {i} messages read", file=sys.stderr, flush=True)
    for topic in reader.types:
        if reader.topics is None or topic in reader.topics:
            per_topic.setdefault(topic, [])
    for items in per_topic.values():
        items.sort(key=lambda item: item[0])
    types = {t: n for t, n in reader.types.items() if t in per_topic}
    return Bag(Path(path), per_topic, types, reader.finished, reader.reports)

