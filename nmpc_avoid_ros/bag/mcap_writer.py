"""MCAP bags written the way rosbag2 writes them (no running ROS graph needed).

`Ros2McapWriter` takes CDR bytes, e.g. straight from a `raw=True` subscription: profile ``ros2``,
one schema per type (encoding ``ros2msg``, see `msg_definitions`), channels with message encoding
``cdr`` and metadata ``offered_qos_profiles``, zstd-compressed chunks. Times are ns. Every chunk
goes to the kernel unbuffered, so a killed writer leaves a file `mcap_io.load_bag` recovers.
"""

from __future__ import annotations

import errno
import os
from collections import Counter
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from .mcap_io import BagError
from .msg_definitions import message_definition, msg_search_paths, normalize_type

#: rosbag2's default MCAP chunk size (the storage plugin's default), bytes
DEFAULT_CHUNK_SIZE = 768 * 1024
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


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

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write an MCAP metadata record (`name`, string keys -> string values) at once, outside the chunks:
        it is in the kernel when this returns, so an unfinished file keeps it too."""
        self._guard(lambda: self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()}))

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
