"""Reading MCAP bags, tolerantly (no running ROS graph needed), and the bag error type.

`read_bag` and `load_bag` decode with `mcap_ros2`. A file that was never finished (the recorder was
killed, the disk filled up) has no summary and no footer: it is read record by record and every
complete chunk is kept; the result says ``finished=False``. Anything that is not an MCAP file, or is
cut inside its header, raises `BagError` with a plain reason. Writing is `mcap_writer`; the schema
texts are `msg_definitions`.
"""

from __future__ import annotations

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
from mcap.records import Channel, Chunk, Footer, Header, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader, breakup_chunk

from ..core.errors import NmpcError

MAGIC = b"\x89MCAP0\r\n"


class BagError(NmpcError):
    """A bag cannot be written or read; the message names the file and the reason."""


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
    `finished` is known then; the per-file `reports` (chunks kept, damaged chunks) and the MCAP
    metadata records (`metadata`: (name, {key: value}) in file order, a record repeated in a later
    split file kept once) after iterating.
    """

    def __init__(self, path: str | os.PathLike, topics: Iterable[str] | None = None, *, decode: bool = True) -> None:
        self.path = Path(path)
        self.topics = None if topics is None else set(topics)
        self.decode = decode
        self.reports = [_check_file(p) for p in _bag_files(self.path)]
        self.types: dict[str, str] = {}
        self.metadata: list[tuple[str, dict[str, str]]] = []

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
            elif isinstance(record, Metadata):
                entry = (str(record.name), {str(k): str(v) for k, v in dict(record.metadata).items()})
                if entry not in self.metadata:
                    self.metadata.append(entry)
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
    """A bag in memory: per topic, the (log_time_ns, message) pairs sorted by log time; the MCAP
    metadata records (name, {key: value}), e.g. the nodes' parameters (bag/node_parameters.py)."""

    path: Path
    topics: dict[str, list[tuple[int, Any]]]
    types: dict[str, str]
    finished: bool
    files: list[FileReport]
    metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)

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
    return Bag(Path(path), per_topic, types, reader.finished, reader.reports, reader.metadata)
