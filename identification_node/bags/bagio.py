"""rosbag2 (ROS 2 Jazzy) bag reading and writing without rclpy, on top of `rosbags` and `mcap`.

Reading streams message by message (memory does not grow with the bag length).
``sensor_msgs/msg/JointState`` has a specialised CDR decoder (struct + np.frombuffer),
about 5x faster than the rosbags deserializer, which stays the reference and the fallback
(big-endian data, anything the fast path does not accept). ``iter_joint_state_blocks``
reads one JointState topic of an indexed mcap bag a chunk at a time (the mcap library's
reader: summary, chunk records, decompression and checksum) and decodes runs of messages of
one layout at once (another ~10x); it yields what ``iter_joint_states`` yields. The node's
polled messages are decoded the same way (``decode_joint_states``). Only public APIs of
rosbags (Reader, Writer, typesys) and mcap are used.

Writing goes into a hidden temporary sibling directory that is renamed into place on a
successful close, so a bag path either holds a complete bag or nothing.

Times: ``*_ns`` are integer nanoseconds, other times float seconds; a bag's log time is
the receive time stored by the recorder, ``stamp`` the message's ``header.stamp``.
"""
from __future__ import annotations

import functools
import math
import shutil
import struct
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

import numpy as np
import yaml

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability
from rosbags.interfaces import QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from identification_node.bags.mcap_check import add_chunk_crcs, verify_chunks
from identification_node.errors import IdentificationError
from identification_node.wire.records import JointStateRecord

JOINT_STATE = 'sensor_msgs/msg/JointState'
STRING = 'std_msgs/msg/String'
CLOCK = 'rosgraph_msgs/msg/Clock'
FLOAT64_MULTI_ARRAY = 'std_msgs/msg/Float64MultiArray'
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'
JOINT_TRAJECTORY = 'trajectory_msgs/msg/JointTrajectory'

STORAGES = ('mcap', 'sqlite3')
_STORAGE_FILES = ('.mcap', '.db3')
_BAG_VERSION = 9  # rosbag2 metadata version written by Jazzy

__all__ = [
    'BagReader', 'BagWriter', 'JointStateDecoder', 'open_bag',
    'iter_joint_states', 'iter_joint_state_blocks', 'iter_messages', 'iter_raw',
    'read_string_topic',
    'decode_joint_state', 'decode_joint_state_reference', 'decode_joint_states',
    'decode_rows', 'deserialize_cdr',
    'encode_joint_state', 'encode_joint_states', 'jazzy_typestore', 'make_time',
    'make_duration', 'make_header',
    'make_joint_state', 'make_string', 'make_clock', 'make_float64_multi_array',
    'make_diagnostic_array', 'make_joint_trajectory',
]


@functools.lru_cache(maxsize=1)
def jazzy_typestore() -> Typestore:
    """Shared rosbags typestore of the ROS 2 Jazzy message types (do not register into it)."""
    return get_typestore(Stores.ROS2_JAZZY)


# ----------------------------------------------------------------------------------------
# CDR decoding
# ----------------------------------------------------------------------------------------

_HEAD = struct.Struct('<iII')  # header.stamp.sec, header.stamp.nanosec, len(frame_id)
_U32 = struct.Struct('<I')
_F8 = np.dtype('<f8')
_EMPTY = np.empty(0)
_EMPTY.flags.writeable = False


class _Malformed(Exception):
    """The fast path does not accept this buffer (the reference decoder decides)."""


def deserialize_cdr(typestore: Typestore, raw: bytes | memoryview, msgtype: str) -> Any:
    """Deserialize one CDR message with rosbags, tolerating trailing padding bytes.

    rosbags rejects buffers longer than the message plus alignment, which
    ``rclpy.serialization.serialize_message`` produces (it reports the estimated size).
    Raises IdentificationError on malformed data or an unknown type.
    """
    try:
        msgdef = typestore.get_msgdef(msgtype)
    except Exception as err:
        raise IdentificationError(f'unknown message type {msgtype!r}: {err}') from None
    if len(raw) < 4 or raw[0] != 0 or raw[1] not in (0, 1):
        raise IdentificationError(
            f'{msgtype} message is not CDR data (bad encapsulation header {bytes(raw[:4])!r})')
    func = msgdef.deserialize_cdr_le if raw[1] else msgdef.deserialize_cdr_be
    try:
        msg, _ = func(memoryview(raw)[4:], 0, msgdef.cls, typestore)
    except Exception as err:
        raise IdentificationError(
            f'corrupt {msgtype} message ({len(raw)} bytes): {err}') from None
    return msg


def decode_joint_state_reference(raw: bytes | memoryview) -> JointStateRecord:
    """Decode sensor_msgs/JointState CDR with the rosbags deserializer (reference path)."""
    msg = deserialize_cdr(jazzy_typestore(), raw, JOINT_STATE)
    stamp = msg.header.stamp
    return JointStateRecord(
        stamp.sec * 1_000_000_000 + stamp.nanosec, tuple(msg.name),
        np.asarray(msg.position, dtype=np.float64), np.asarray(msg.velocity, dtype=np.float64),
        np.asarray(msg.effort, dtype=np.float64))


class JointStateDecoder:
    """Fast decoder of little-endian sensor_msgs/JointState CDR.

    Layout after the 4-byte encapsulation header (alignment relative to its end): int32 sec,
    uint32 nanosec, string frame_id, sequence<string> name, 3 x sequence<float64>; a float64
    sequence is 8-aligned only when non-empty. Keeps the last name-sequence bytes to reuse
    the decoded names tuple (one C-level comparison instead of decoding every name).
    One instance per stream (not shared across threads).
    """

    def __init__(self) -> None:
        # (CDR bytes of the name sequence, decoded names); the sentinel never matches
        self._names: tuple[bytes, tuple[str, ...]] = (b'\xff' * 9, ())

    def __call__(self, raw: bytes | memoryview) -> JointStateRecord:
        """Decode one message; falls back to the rosbags deserializer if needed."""
        if type(raw) is not bytes:
            raw = bytes(raw)
        if raw[:2] == b'\x00\x01':
            try:
                return self._fast(raw)
            except (_Malformed, struct.error, ValueError, UnicodeDecodeError):
                pass
        return decode_joint_state_reference(raw)

    def _fast(self, data: bytes, spans: list | None = None) -> JointStateRecord:
        """Decode; ``spans`` (if given) gets the (byte offset, count) of the three arrays."""
        n = len(data)
        sec, nsec, flen = _HEAD.unpack_from(data, 4)
        p = 16 + flen
        if flen == 0 or p > n or data[p - 1]:
            raise _Malformed
        p = (p + 3) & -4
        blob, names = self._names
        if data.startswith(blob, p):
            p += len(blob)
        else:
            start = p
            (count,) = _U32.unpack_from(data, p)
            p += 4
            if 5 * count > n - p:
                raise _Malformed
            lst = []
            for _ in range(count):
                p = (p + 3) & -4
                (length,) = _U32.unpack_from(data, p)
                end = p + 4 + length
                if length == 0 or end > n or data[end - 1]:
                    raise _Malformed
                lst.append(data[p + 4:end - 1].decode())
                p = end
            names = tuple(lst)
            self._names = (data[start:p], names)
        frombuffer, unpack = np.frombuffer, _U32.unpack_from
        # three float64 sequences, unrolled: the hot path of bag reading
        p = (p + 3) & -4
        (count,) = unpack(data, p)
        p += 4
        if count:
            p = ((p + 3) & -8) + 4  # 8-align relative to the body start at offset 4
            position = frombuffer(data, _F8, count, p)
            if spans is not None:
                spans.append((p, count))
            p += 8 * count
        else:
            position = _EMPTY
            if spans is not None:
                spans.append((p, 0))
        p = (p + 3) & -4
        (count,) = unpack(data, p)
        p += 4
        if count:
            p = ((p + 3) & -8) + 4
            velocity = frombuffer(data, _F8, count, p)
            if spans is not None:
                spans.append((p, count))
            p += 8 * count
        else:
            velocity = _EMPTY
            if spans is not None:
                spans.append((p, 0))
        p = (p + 3) & -4
        (count,) = unpack(data, p)
        if count:
            effort = frombuffer(data, _F8, count, ((p + 7) & -8) + 4)
            if spans is not None:
                spans.append((((p + 7) & -8) + 4, count))
        else:
            effort = _EMPTY
            if spans is not None:
                spans.append((p, 0))
        return JointStateRecord(sec * 1_000_000_000 + nsec, names, position, velocity, effort)


def decode_joint_state(raw: bytes | memoryview) -> JointStateRecord:
    """Decode one sensor_msgs/JointState CDR buffer (fast path, rosbags fallback)."""
    return JointStateDecoder()(raw)


# ----------------------------------------------------------------------------------------
# Reading
# ----------------------------------------------------------------------------------------

def _reader_error(path: Path, err: BaseException) -> IdentificationError:
    """Translate a rosbags/storage exception into a readable IdentificationError."""
    text = str(err) or type(err).__name__
    low = text.lower()
    if isinstance(err, OSError):
        hint = 'cannot open a file of the bag'
    elif 'missing' in low and 'files' in low:
        hint = 'storage files listed in metadata.yaml are missing'
    elif 'end magic' in low or 'footer' in low or 'truncated' in low:
        hint = ('the mcap file is truncated or corrupt (recording interrupted?); '
                '`mcap recover IN.mcap -o OUT.mcap` (mcap CLI) may salvage it')
    elif 'magic' in low or 'profile' in low:
        hint = 'not a ROS 2 mcap file'
    elif 'database' in low or 'notadb' in low or 'sqlite' in low:
        hint = 'the sqlite3 storage file is corrupt or not a rosbag2 database'
    elif 'storage plugin' in low or 'unrecognized storage' in low:
        hint = f'unsupported storage (supported: {", ".join(STORAGES)})'
    elif 'metadata' in low or 'yaml' in low:
        hint = 'invalid metadata.yaml'
    elif 'empty' in low:
        hint = 'the storage file is empty'
    else:
        hint = 'cannot read the bag'
    return IdentificationError(f'bag {str(path)!r}: {hint} ({text})')


def _storage_target(path: Path) -> Path:
    """Return what rosbags should open for ``path``: a bag directory or a lone storage file."""
    if not path.exists():
        raise IdentificationError(f'bag {str(path)!r} does not exist')
    if path.is_file():
        if path.suffix not in _STORAGE_FILES:
            raise IdentificationError(
                f'bag {str(path)!r}: not a rosbag2 directory nor a .mcap/.db3 storage file')
        return path
    if (path / 'metadata.yaml').is_file():
        return path
    files = sorted(p for p in path.iterdir() if p.suffix in _STORAGE_FILES and p.is_file())
    if len(files) == 1:
        return files[0]
    if not files:
        raise IdentificationError(
            f'bag {str(path)!r}: not a rosbag2 bag (no metadata.yaml and no .mcap/.db3 file)')
    raise IdentificationError(
        f'bag {str(path)!r}: no metadata.yaml and several storage files '
        f'({", ".join(p.name for p in files)}); restore metadata.yaml with '
        '`ros2 bag reindex` or pass one storage file')


class BagReader:
    """Open rosbag2 bag (directory with metadata.yaml, or a lone .mcap/.db3 file).

    Opens on construction (errors surface as IdentificationError); use as a context manager
    or call close(). Attributes: path, topics {topic: msgtype}, topic_counts {topic: n},
    message_count, start_ns/end_ns (first/last log time), start_time/end_time [s], duration.
    """

    def __init__(self, path: str | Path, *, allow_empty: bool = False) -> None:
        self.path = Path(path)
        self._files: list[BinaryIO] = []
        target = _storage_target(self.path)
        try:
            self._reader = Reader(target)
            self._reader.open()
            # chunk checksums before any message: corruption is an error naming the chunk
            files = sorted(target.glob('*.mcap')) if target.is_dir() else [target]
            self.unverified_chunks = sum(verify_chunks(f) for f in files
                                         if f.suffix == '.mcap')
        except IdentificationError:
            raise
        except Exception as err:
            raise _reader_error(self.path, err) from None
        try:
            self._setup(allow_empty)
        except BaseException:
            self.close()
            raise

    def _setup(self, allow_empty: bool) -> None:
        reader = self._reader
        self._connections = list(reader.connections)
        self.topics: dict[str, str] = {}
        self.topic_counts: dict[str, int] = {}
        for conn in self._connections:
            if self.topics.setdefault(conn.topic, conn.msgtype) != conn.msgtype:
                raise IdentificationError(
                    f'bag {str(self.path)!r}: topic {conn.topic!r} carries several message '
                    f'types ({self.topics[conn.topic]}, {conn.msgtype})')
            self.topic_counts[conn.topic] = self.topic_counts.get(conn.topic, 0) + conn.msgcount
        self.message_count = int(reader.message_count)
        if self.message_count == 0:
            self.start_ns = self.end_ns = 0
            if not allow_empty:
                raise IdentificationError(f'bag {str(self.path)!r} contains no messages')
        else:
            self.start_ns = int(reader.start_time)
            self.end_ns = int(reader.end_time) - 1  # rosbags reports last time + 1 ns
        self.typestore = self._make_typestore()

    def _make_typestore(self) -> Typestore:
        """Jazzy types plus the bag's embedded definitions of types Jazzy does not know."""
        base = jazzy_typestore()
        extra: dict[str, Any] = {}
        for conn in self._connections:
            if conn.msgtype in base.types or not conn.msgdef.data:
                continue
            try:
                if conn.msgdef.format.name == 'MSG':
                    extra.update(get_types_from_msg(conn.msgdef.data, conn.msgtype))
                else:
                    sep = '=' * 80 + '\n'
                    for part in conn.msgdef.data.split(sep):
                        if part.startswith('IDL: '):
                            part = part.split('\n', 1)[1]
                        if part.strip():
                            extra.update(get_types_from_idl(part))
            except Exception:  # an unparsable definition only matters if it is read
                continue
        if not extra:
            return base
        store = get_typestore(Stores.ROS2_JAZZY)
        try:
            store.register({k: v for k, v in extra.items() if k not in base.types})
        except Exception:
            return base
        return store

    @property
    def start_time(self) -> float:
        """First log time [s] (0 for an empty bag)."""
        return self.start_ns * 1e-9

    @property
    def end_time(self) -> float:
        """Last log time [s] (0 for an empty bag)."""
        return self.end_ns * 1e-9

    @property
    def duration(self) -> float:
        """Last minus first log time [s]."""
        return (self.end_ns - self.start_ns) * 1e-9

    def check_topics(self, topics: Iterable[str], msgtype: str | None = None) -> list[str]:
        """Return topics as a list; IdentificationError if one is missing or mistyped."""
        topics = [topics] if isinstance(topics, str) else list(topics)
        for topic in topics:
            if topic not in self.topics:
                have = ', '.join(f'{t} [{m}]' for t, m in sorted(self.topics.items()))
                raise IdentificationError(
                    f'topic {topic!r} is not in bag {str(self.path)!r}; '
                    f'available topics: {have or "none"}')
            if msgtype is not None and self.topics[topic] != msgtype:
                raise IdentificationError(
                    f'topic {topic!r} in bag {str(self.path)!r} carries '
                    f'{self.topics[topic]}, expected {msgtype}')
        return topics

    def raw_messages(self, topics: Iterable[str] | None = None
                     ) -> Iterator[tuple[str, str, int, bytes]]:
        """Yield (topic, msgtype, log_time_ns, cdr_bytes) in log-time order (all if None)."""
        if self._reader is None:
            raise IdentificationError(f'bag {str(self.path)!r} is closed')
        wanted = None if topics is None else set(self.check_topics(topics))
        conns = [c for c in self._connections if wanted is None or c.topic in wanted]
        if not conns:
            return
        try:
            for conn, t_ns, raw in self._reader.messages(conns):
                yield conn.topic, conn.msgtype, t_ns, raw
        except IdentificationError:
            raise
        except Exception as err:
            raise _reader_error(self.path, err) from None

    def open_storage_file(self, path: Path) -> BinaryIO:
        """One of the bag's storage files opened for reading (binary), closed with the bag."""
        stream = open(path, 'rb')
        self._files.append(stream)
        return stream

    def close(self) -> None:
        """Close the storage files (idempotent)."""
        for stream in getattr(self, '_files', ()):
            stream.close()
        self._files = []
        reader, self._reader = getattr(self, '_reader', None), None
        if reader is not None and reader.is_open:
            reader.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f'BagReader({str(self.path)!r}, {self.message_count} messages, '
                f'{len(self.topics)} topics, {self.duration:.3f} s)')


def open_bag(path: str | Path, *, allow_empty: bool = False) -> BagReader:
    """Open a rosbag2 bag for reading (see BagReader)."""
    return BagReader(path, allow_empty=allow_empty)


def iter_raw(reader: BagReader, topics: Iterable[str] | None = None
             ) -> Iterator[tuple[str, str, int, bytes]]:
    """Yield (topic, msgtype, log_time_ns, cdr_bytes) in log-time order."""
    return reader.raw_messages(topics)


def iter_messages(reader: BagReader, topics: Iterable[str] | None = None
                  ) -> Iterator[tuple[str, str, int, Any]]:
    """Yield (topic, msgtype, log_time_ns, rosbags message) in log-time order."""
    store = reader.typestore
    for topic, msgtype, t_ns, raw in reader.raw_messages(topics):
        try:
            yield topic, msgtype, t_ns, deserialize_cdr(store, raw, msgtype)
        except IdentificationError as err:
            raise IdentificationError(f'topic {topic!r} at log time {t_ns} ns: {err}') from None


def iter_joint_states(reader: BagReader, topics: str | Iterable[str]
                      ) -> Iterator[tuple[str, int, JointStateRecord]]:
    """Yield (topic, log time ns, record) in log-time order across JointState topics."""
    topics = reader.check_topics(topics, JOINT_STATE)
    decoders = {t: JointStateDecoder() for t in topics}
    for topic, _, t_ns, raw in reader.raw_messages(topics):
        try:
            yield topic, t_ns, decoders[topic](raw)
        except IdentificationError as err:
            raise IdentificationError(f'topic {topic!r} at log time {t_ns} ns: {err}') from None


# ----------------------------------------------------------------------------------------
# Block reading: runs of same-layout JointState messages from indexed mcap chunks
# ----------------------------------------------------------------------------------------

_RECORD = struct.Struct('<BQ')  # mcap record head: opcode, body length
_MESSAGE = 0x05                 # mcap message record; its body: channel id (u16), sequence
_MESSAGE_HEAD = 22              # (u32), log time (u64), publish time (u64), then the data
_MAX_BLOCK = 4096               # rows compared (and decoded) at once


def iter_joint_state_blocks(reader: BagReader, topic: str
                            ) -> Iterator[tuple[np.ndarray, JointStateRecord]]:
    """The messages of ``iter_joint_states(reader, [topic])``, in the same order with the
    same values and errors, as (log times ns (M,), record). Consecutive messages sharing their
    layout (frame_id, names, array lengths) come as one block record: stamp_ns (M,) int64 and
    (M, k) arrays, decoded at once from the bag's indexed mcap chunks (one chunk in memory at a
    time). Other messages come one by one (M = 1, a plain record), and so do all messages of
    bags this does not handle (sqlite3, unindexed or time-overlapping chunks, per-message
    compression)."""
    reader.check_topics([topic], JOINT_STATE)
    storages = _mcap_storages(reader, topic)
    if storages is None:
        for _, t_ns, record in iter_joint_states(reader, [topic]):
            yield np.array([t_ns]), record
        return
    decoder = JointStateDecoder()
    for stream, summary, ids in storages:
        for chunk in _chunks(summary, ids):
            try:
                buf = _read_chunk(stream, chunk)
                found = _message_records(buf)
            except Exception as err:
                raise _reader_error(reader.path, err) from None
            yield from _chunk_blocks(buf, *found, ids, chunk, decoder, topic)


def _mcap_files(reader: BagReader) -> list[Path] | None:
    """The bag's storage files when they are plain mcap (rosbag2 metadata.yaml, or a lone
    .mcap file), else None."""
    path = reader.path
    if path.is_file():
        return [path] if path.suffix == '.mcap' else None
    if not (path / 'metadata.yaml').is_file():
        lone = _storage_target(path)
        return [lone] if lone.suffix == '.mcap' else None
    info = yaml.safe_load((path / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    if info.get('storage_identifier') != 'mcap' or info.get('compression_mode'):
        return None
    return [path / name for name in info['relative_file_paths']]


def _mcap_storages(reader: BagReader, topic: str
                   ) -> list[tuple[BinaryIO, Any, set[int]]] | None:
    """(open file, mcap summary, channel ids of ``topic``) of each storage file in reading order,
    or None when block reading would not reproduce the reader's message order (sqlite3, file
    or message compression, no chunk index, chunks overlapping in time)."""
    from mcap.reader import make_reader
    files = _mcap_files(reader)
    if files is None:
        return None
    out = []
    for path in files:
        stream = reader.open_storage_file(path)
        storage = make_reader(stream, validate_crcs=True)
        try:
            summary = storage.get_summary()
        except Exception:   # no summary: read message by message
            return None
        if summary is None or not summary.chunk_indexes:
            return None
        ids = {i for i, c in summary.channels.items() if c.topic == topic}
        chunks = _chunks(summary, ids)
        # rosbags merges the chunks by (log time, chunk offset): in index order here
        if any(b.message_start_time < a.message_end_time
               or (b.message_start_time == a.message_end_time
                   and b.chunk_start_offset < a.chunk_start_offset)
               for a, b in zip(chunks, chunks[1:])):
            return None
        out.append((stream, summary, ids))
    return out


def _chunks(summary: Any, ids: set[int]) -> list:
    """The chunk indexes of an mcap summary holding messages of the channels ``ids``, in
    file order."""
    return sorted((c for c in summary.chunk_indexes if ids & set(c.message_index_offsets)),
                  key=lambda c: c.chunk_start_offset)


def _read_chunk(stream: BinaryIO, chunk: Any) -> bytes:
    """The decompressed, checksum-verified records of an mcap chunk (mcap's reader)."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk
    from mcap.stream_reader import get_chunk_data_stream
    stream.seek(chunk.chunk_start_offset + 1 + 8)   # the record's opcode and length
    data, size = get_chunk_data_stream(Chunk.read(ReadDataStream(stream)), validate_crc=True)
    return data.read(size)


def _message_records(buf: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Body offsets and body lengths of the message records in an mcap chunk's records. Runs
    of records with the same head (opcode and length) are found by numpy, not one by one."""
    a = np.frombuffer(buf, np.uint8)
    end, p = len(buf), 0
    starts, lengths = [], []
    while p + 9 <= end:
        op, ln = _RECORD.unpack_from(buf, p)
        stride = 9 + ln
        if p + stride > end:
            raise IdentificationError('mcap chunk truncated: a record exceeds it')
        if op == _MESSAGE:
            m = 1
            if buf[p + stride:p + stride + 9] == buf[p:p + 9]:
                m = _same_records(a, p, stride, end)
            starts.append(p + 9 + stride * np.arange(m))
            lengths.append(np.full(m, ln))
            p += stride * m
        else:
            p += stride
    if not starts:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    body, length = np.concatenate(starts), np.concatenate(lengths).astype(np.int64)
    if np.any(length < _MESSAGE_HEAD):
        raise IdentificationError(f'invalid message record length {int(length.min())}')
    return body, length


def _same_records(a: np.ndarray, p: int, stride: int, end: int) -> int:
    """How many consecutive records from offset p have the head of the one at p (galloping)."""
    total, m, step = (end - p) // stride, 1, 8
    while m < total:
        k = min(step, total - m)
        heads = a[p + m * stride:p + (m + k) * stride].reshape(k, stride)[:, :9]
        same = (heads == a[p:p + 9]).all(axis=1)
        if not same.all():
            return m + int(np.argmin(same))
        m, step = m + k, step * 8
    return m


def _gather(a: np.ndarray, offsets: np.ndarray, width: int) -> np.ndarray:
    """Rows a[o:o + width] for the offsets, (M, width): a strided view when equally spaced."""
    d = np.diff(offsets)
    if len(offsets) > 1 and d[0] >= width and np.all(d == d[0]):
        return np.lib.stride_tricks.as_strided(a[offsets[0]:], (len(offsets), width),
                                               (int(d[0]), 1), writeable=False)
    if len(offsets) == 1:
        return a[offsets[0]:offsets[0] + width][None]
    return a[offsets[:, None] + np.arange(width)]


def _fields(a: np.ndarray, offsets: np.ndarray, dtype: str) -> np.ndarray:
    """One little-endian field at each offset of a (uint8), as (M,) dtype."""
    size = np.dtype(dtype).itemsize
    return a[offsets[:, None] + np.arange(size)].view(dtype)[:, 0]


def _chunk_blocks(buf: bytes, body: np.ndarray, length: np.ndarray, ids: set[int], chunk: Any,
                  decoder: JointStateDecoder, topic: str
                  ) -> Iterator[tuple[np.ndarray, JointStateRecord]]:
    """The topic's messages in a chunk in rosbags' order (stable by log time, within the
    chunk's declared time range), decoded in blocks of equal layout."""
    a = np.frombuffer(buf, np.uint8)
    channel = _fields(a, body, '<u2')
    log = _fields(a, body + 6, '<u8').astype(np.int64)
    keep = (np.isin(channel, list(ids)) & (log >= chunk.message_start_time)
            & (log <= chunk.message_end_time))
    body, length, log = body[keep], length[keep], log[keep]
    order = np.argsort(log, kind='stable')
    body, length, log = body[order] + _MESSAGE_HEAD, length[order] - _MESSAGE_HEAD, log[order]
    cuts = np.flatnonzero(np.diff(length)) + 1
    for first, stop in zip(np.r_[0, cuts], np.r_[cuts, len(length)]):
        rows = _gather(a, body[first:stop], int(length[first]))
        yield from _same_layout_blocks(rows, log[first:stop], decoder, topic)


def _same_layout_blocks(rows: np.ndarray, log: np.ndarray, decoder: JointStateDecoder,
                        topic: str) -> Iterator[tuple[np.ndarray, JointStateRecord]]:
    """The decoded blocks of rows (M, L) of a bag's topic; a message that cannot be decoded
    raises IdentificationError naming the topic and its log time."""
    for start, stop, record in decode_rows(rows, decoder):
        if isinstance(record, IdentificationError):
            raise IdentificationError(
                f'topic {topic!r} at log time {int(log[start])} ns: {record}') from None
        yield log[start:stop], record


def decode_rows(rows: np.ndarray, decoder: JointStateDecoder
                ) -> Iterator[tuple[int, int, JointStateRecord | IdentificationError]]:
    """JointState messages of equal length, rows (M, L) uint8, as (start, stop, record):
    runs of rows whose bytes agree everywhere but in the stamp and the array values share the
    first one's layout and come as one block record (stamp_ns (M,) int64, (M, k) arrays);
    other rows one by one (a plain record), or the IdentificationError that says why a row
    cannot be decoded."""
    k = 0
    while k < len(rows):
        raw = rows[k].tobytes()
        spans: list = []
        try:
            record = decoder._fast(raw, spans) if raw[:2] == b'\x00\x01' else None
        except (_Malformed, struct.error, ValueError, UnicodeDecodeError):
            record = None
        if record is None:  # the reference decoder decides (and words the error)
            try:
                record = decoder(raw)
            except IdentificationError as err:
                record = err
            yield k, k + 1, record
            k += 1
            continue
        layout = np.ones(rows.shape[1], dtype=bool)
        layout[4:12] = False  # header.stamp
        for offset, count in spans:
            layout[offset:offset + 8 * count] = False
        ahead = rows[k + 1:k + _MAX_BLOCK]
        same = (ahead[:, layout] == rows[k, layout]).all(axis=1)
        m = 1 + (len(same) if same.all() else int(np.argmin(same)))
        if m == 1:
            yield k, k + 1, record
        else:
            block = np.ascontiguousarray(rows[k:k + m])
            stamps = (block[:, 4:8].copy().view('<i4')[:, 0].astype(np.int64) * 1_000_000_000
                      + block[:, 8:12].copy().view('<u4')[:, 0])
            arrays = [block[:, o:o + 8 * c].copy().view('<f8') if c else np.empty((m, 0))
                      for o, c in spans]
            yield k, k + m, JointStateRecord(stamps, record.names, *arrays)
        k += m


def decode_joint_states(messages: Sequence[bytes], decoder: JointStateDecoder
                        ) -> Iterator[JointStateRecord | IdentificationError]:
    """JointState CDR messages in order (a subscription's poll), decoded: runs of one layout
    as block records (decode_rows), the others one by one, or the IdentificationError of a
    message that cannot be decoded. The same decoder as bag reading."""
    i = 0
    while i < len(messages):
        size = len(messages[i])
        j = i + 1
        while j < len(messages) and len(messages[j]) == size:
            j += 1
        if j - i == 1:
            try:
                yield decoder(messages[i])
            except IdentificationError as err:
                yield err
        else:
            rows = np.frombuffer(b''.join(messages[i:j]), np.uint8).reshape(j - i, size)
            for _, _, record in decode_rows(rows, decoder):
                yield record
        i = j


def read_string_topic(reader: BagReader, topic: str = '/robot_description') -> str | None:
    """Return the last std_msgs/String on topic, or None if the topic is absent or empty."""
    if topic not in reader.topics:
        return None
    reader.check_topics([topic], STRING)
    last = None
    for _, _, _, msg in iter_messages(reader, [topic]):
        last = msg.data
    return last


# ----------------------------------------------------------------------------------------
# Message construction
# ----------------------------------------------------------------------------------------

def _sec_nsec(t: float) -> tuple[int, int]:
    """Split float seconds into (sec, nanosec) with 0 <= nanosec < 1e9."""
    if not math.isfinite(t):
        raise IdentificationError(f'time {t!r} is not finite')
    sec = math.floor(t)
    nsec = round((t - sec) * 1e9)
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return int(sec), int(nsec)


def make_time(t: float, typestore: Typestore | None = None) -> Any:
    """builtin_interfaces/Time from float seconds."""
    sec, nsec = _sec_nsec(t)
    return (typestore or jazzy_typestore()).types['builtin_interfaces/msg/Time'](sec, nsec)


def make_duration(t: float, typestore: Typestore | None = None) -> Any:
    """builtin_interfaces/Duration from float seconds."""
    sec, nsec = _sec_nsec(t)
    return (typestore or jazzy_typestore()).types['builtin_interfaces/msg/Duration'](sec, nsec)


def make_header(stamp: float, frame_id: str = '', typestore: Typestore | None = None) -> Any:
    """std_msgs/Header with stamp [s]."""
    ts = typestore or jazzy_typestore()
    return ts.types['std_msgs/msg/Header'](make_time(stamp, ts), frame_id)


def _f64(values: Iterable[float]) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(values, dtype=np.float64).reshape(-1))


def make_joint_state(stamp: float, names: Sequence[str], position: Iterable[float] = (),
                     velocity: Iterable[float] = (), effort: Iterable[float] = (),
                     frame_id: str = '', typestore: Typestore | None = None) -> Any:
    """sensor_msgs/JointState (rosbags object) from SI values."""
    ts = typestore or jazzy_typestore()
    return ts.types[JOINT_STATE](make_header(stamp, frame_id, ts), list(names), _f64(position),
                                 _f64(velocity), _f64(effort))


def make_string(text: str, typestore: Typestore | None = None) -> Any:
    """std_msgs/String."""
    return (typestore or jazzy_typestore()).types[STRING](text)


def make_clock(t: float, typestore: Typestore | None = None) -> Any:
    """rosgraph_msgs/Clock at t [s]."""
    ts = typestore or jazzy_typestore()
    return ts.types[CLOCK](make_time(t, ts))


def make_float64_multi_array(data: Iterable[float], labels: Sequence[str] = (),
                             typestore: Typestore | None = None) -> Any:
    """std_msgs/Float64MultiArray; ``data`` is flattened in C order, one layout dimension per
    label with the sizes of ``np.shape(data)`` (labels must match the number of dims)."""
    ts = typestore or jazzy_typestore()
    arr = np.asarray(data, dtype=np.float64)
    dims = []
    if labels:
        if len(labels) != arr.ndim:
            raise IdentificationError(
                f'{len(labels)} labels for a {arr.ndim}-dimensional array')
        strides = np.cumprod(arr.shape[::-1])[::-1]
        dim_t = ts.types['std_msgs/msg/MultiArrayDimension']
        dims = [dim_t(lab, int(size), int(stride))
                for lab, size, stride in zip(labels, arr.shape, strides)]
    layout = ts.types['std_msgs/msg/MultiArrayLayout'](dims, 0)
    return ts.types[FLOAT64_MULTI_ARRAY](layout, _f64(arr))


def make_diagnostic_array(stamp: float,
                          statuses: Iterable[tuple[int, str, str, str, dict[str, str]]],
                          typestore: Typestore | None = None) -> Any:
    """diagnostic_msgs/DiagnosticArray from (level, name, message, hardware_id, {key: value})
    tuples; level 0 OK, 1 WARN, 2 ERROR, 3 STALE."""
    ts = typestore or jazzy_typestore()
    kv_t = ts.types['diagnostic_msgs/msg/KeyValue']
    st_t = ts.types['diagnostic_msgs/msg/DiagnosticStatus']
    status = [st_t(int(level), name, message, hw, [kv_t(str(k), str(v)) for k, v in kv.items()])
              for level, name, message, hw, kv in statuses]
    return ts.types[DIAGNOSTIC_ARRAY](make_header(stamp, '', ts), status)


def make_joint_trajectory(stamp: float, joint_names: Sequence[str],
                          times: Iterable[float], positions: Any,
                          velocities: Any = None, accelerations: Any = None,
                          efforts: Any = None, typestore: Typestore | None = None) -> Any:
    """trajectory_msgs/JointTrajectory; times [s] from start (K,), positions etc. (K, n)."""
    ts = typestore or jazzy_typestore()
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    k, n = len(times), len(joint_names)

    def rows(values: Any, what: str) -> np.ndarray:
        if values is None:
            return np.empty((k, 0))
        arr = np.asarray(values, dtype=np.float64)
        if arr.shape != (k, n):
            raise IdentificationError(f'trajectory {what} has shape {arr.shape}, need {(k, n)}')
        return arr

    pos, vel = rows(positions, 'positions'), rows(velocities, 'velocities')
    acc, eff = rows(accelerations, 'accelerations'), rows(efforts, 'efforts')
    pt_t = ts.types['trajectory_msgs/msg/JointTrajectoryPoint']
    points = [pt_t(_f64(pos[i]), _f64(vel[i]), _f64(acc[i]), _f64(eff[i]),
                   make_duration(float(times[i]), ts)) for i in range(k)]
    return ts.types[JOINT_TRAJECTORY](make_header(stamp, '', ts), list(joint_names), points)


# ----------------------------------------------------------------------------------------
# Fast JointState CDR encoding
# ----------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=64)
def _names_cdr(names: tuple[str, ...]) -> bytes:
    """CDR of a sequence<string> starting 4-aligned (its inner padding is then fixed)."""
    buf = bytearray(_U32.pack(len(names)))
    for name in names:
        enc = name.encode() + b'\0'
        buf += b'\0' * (-len(buf) % 4) + _U32.pack(len(enc)) + enc
    return bytes(buf)


def _f64_cdr(values: Iterable[float], pos: int) -> tuple[bytes, int]:
    """CDR of a sequence<float64> starting 4-aligned at body offset pos; (bytes, new pos)."""
    arr = np.asarray(values, dtype=_F8).reshape(-1)
    if not arr.size:
        return b'\0\0\0\0', pos + 4
    pad = b'\0\0\0\0' if (pos + 4) % 8 else b''
    data = arr.tobytes()
    return _U32.pack(arr.size) + pad + data, pos + 4 + len(pad) + len(data)


def encode_joint_state(stamp: float, names: Sequence[str], position: Iterable[float] = (),
                       velocity: Iterable[float] = (), effort: Iterable[float] = (),
                       frame_id: str = '') -> bytes:
    """Little-endian CDR of sensor_msgs/JointState (byte-identical to rosbags serialize_cdr)."""
    sec, nsec = _sec_nsec(stamp)
    fid = frame_id.encode() + b'\0'
    parts = [b'\x00\x01\x00\x00', _HEAD.pack(sec, nsec, len(fid)), fid,
             b'\0' * (-len(fid) % 4)]
    blob = _names_cdr(tuple(names))
    parts.append(blob)
    pos = 12 + len(fid) + (-len(fid) % 4) + len(blob)  # body offset
    for values in (position, velocity, effort):
        pad = -pos % 4
        chunk, pos = _f64_cdr(values, pos + pad)
        parts += (b'\0' * pad, chunk)
    return b''.join(parts)


@functools.lru_cache(maxsize=64)
def _joint_state_layout(names: tuple[str, ...], counts: tuple[int, int, int]
                        ) -> tuple[np.ndarray, list]:
    """CDR of a JointState with zero stamp and arrays of ``counts`` zeros, as uint8, and the
    (byte offset, count) of its three arrays."""
    template = encode_joint_state(0.0, names, *(np.zeros(c) for c in counts))
    spans: list = []
    JointStateDecoder()._fast(template, spans)
    return np.frombuffer(template, np.uint8), spans


def encode_joint_states(stamps_ns: np.ndarray, names: Sequence[str],
                        position: np.ndarray | None = None, velocity: np.ndarray | None = None,
                        effort: np.ndarray | None = None) -> list[bytes]:
    """encode_joint_state for N messages at once: stamps_ns (N,) integer ns, arrays (N, n) or
    None (an empty field). All messages share one layout, so they are filled in from one
    template, as rows of one numpy byte array; the same bytes as encoding them one by one."""
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    N = len(stamps)
    arrays = [None if a is None else np.ascontiguousarray(a, dtype=_F8)
              for a in (position, velocity, effort)]
    if any(a is not None and (a.ndim != 2 or len(a) != N) for a in arrays):
        raise IdentificationError(f'arrays {[None if a is None else a.shape for a in arrays]} '
                                  f'do not have one row for each of the {N} stamps')
    template, spans = _joint_state_layout(
        tuple(names), tuple(0 if a is None else a.shape[1] for a in arrays))
    rows = np.empty((N, len(template)), dtype=np.uint8)
    rows[:] = template
    head = rows[:, 4:12].view('<u4')
    head[:, 0], head[:, 1] = np.divmod(stamps, 1_000_000_000)  # sec as int32 bits
    for a, (offset, count) in zip(arrays, spans):
        if count:
            rows[:, offset:offset + 8 * count] = a.view(np.uint8)
    return [row.tobytes() for row in rows]


# ----------------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------------

def _qos(latched: bool) -> Qos:
    """Offered QoS profile: reliable; transient_local depth 1 if latched, else volatile."""
    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, 1 if latched else 10, QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               zero, zero, QosLiveliness.AUTOMATIC, zero, False)


class BagWriter:
    """Write a Jazzy rosbag2 bag (metadata.yaml + one .mcap or .db3 file) atomically.

    Messages go to a hidden sibling directory; close() (or leaving the ``with`` block without
    an exception) renames it to ``path``; abort() (or an exception) removes it. An existing
    ``path`` is refused unless overwrite=True (then replaced only on a successful close).
    Times ``time_ns`` are bag log times [ns]; ``stamp`` is header.stamp [s].
    """

    def __init__(self, path: str | Path, storage: str = 'mcap', *, overwrite: bool = False,
                 typestore: Typestore | None = None) -> None:
        self.path = Path(path)
        if storage not in STORAGES:
            raise IdentificationError(
                f'unknown bag storage {storage!r}; use one of {", ".join(STORAGES)}')
        if self.path.exists() and not overwrite:
            raise IdentificationError(
                f'bag {str(self.path)!r} exists already (pass overwrite=True to replace it)')
        if not self.path.name:
            raise IdentificationError(f'invalid bag path {str(self.path)!r}')
        self.storage = storage
        self.overwrite = overwrite
        self.typestore = typestore or jazzy_typestore()
        self.topics: dict[str, str] = {}
        self.message_count = 0
        self._conns: dict[str, Any] = {}
        self._writer: Writer | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._tmp = Path(tempfile.mkdtemp(prefix=f'.{self.path.name}.', suffix='.partial',
                                              dir=self.path.parent))
        except OSError as err:
            raise IdentificationError(f'cannot create bag {str(self.path)!r}: {err}') from None
        try:
            plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
            self._writer = Writer(self._tmp / self.path.name, version=_BAG_VERSION,
                                  storage_plugin=plugin)
            self._writer.open()
        except Exception as err:
            self.abort()
            raise IdentificationError(f'cannot create bag {str(self.path)!r}: {err}') from None

    def add_topic(self, topic: str, msgtype: str, latched: bool = False) -> None:
        """Declare a topic (latched -> transient_local durability, e.g. /robot_description)."""
        writer = self._open_writer()
        if topic in self.topics:
            if self.topics[topic] != msgtype:
                raise IdentificationError(
                    f'topic {topic!r} already added with type {self.topics[topic]}, '
                    f'not {msgtype}')
            return
        if not topic.startswith('/'):
            raise IdentificationError(f'topic name {topic!r} must start with "/"')
        if msgtype not in self.typestore.types:
            raise IdentificationError(f'unknown message type {msgtype!r} for topic {topic!r}')
        self._conns[topic] = writer.add_connection(
            topic, msgtype, typestore=self.typestore, offered_qos_profiles=[_qos(latched)])
        self.topics[topic] = msgtype

    def _open_writer(self) -> Writer:
        if self._writer is None:
            raise IdentificationError(f'bag {str(self.path)!r} is already closed')
        return self._writer

    def _ensure(self, topic: str, msgtype: str) -> None:
        if self.topics.get(topic) != msgtype:
            self.add_topic(topic, msgtype)

    def write_raw(self, topic: str, time_ns: int, cdr: bytes | memoryview) -> None:
        """Write already serialized CDR bytes (e.g. from rclpy) to a declared topic."""
        writer = self._open_writer()
        conn = self._conns.get(topic)
        if conn is None:
            raise IdentificationError(
                f'topic {topic!r} was not declared; call add_topic(topic, msgtype) first')
        time_ns = int(time_ns)
        if time_ns < 0:
            raise IdentificationError(f'negative log time {time_ns} ns on topic {topic!r}')
        writer.write(conn, time_ns, cdr)
        self.message_count += 1

    def write(self, topic: str, time_ns: int, msg: Any) -> None:
        """Serialize and write a rosbags message object (topic declared on first use)."""
        msgtype = getattr(msg, '__msgtype__', None)
        if msgtype is None:
            raise IdentificationError(f'{type(msg).__name__} is not a rosbags message')
        self._ensure(topic, msgtype)
        try:
            cdr = self.typestore.serialize_cdr(msg, msgtype, little_endian=True)
        except Exception as err:
            raise IdentificationError(f'cannot serialize {msgtype} for {topic!r}: {err}') from None
        self.write_raw(topic, time_ns, cdr)

    def write_joint_state(self, topic: str, time_ns: int, stamp: float, names: Sequence[str],
                          position: Iterable[float], velocity: Iterable[float] = (),
                          effort: Iterable[float] = ()) -> None:
        """Write a sensor_msgs/JointState (stamp [s], SI values)."""
        self._ensure(topic, JOINT_STATE)
        self.write_raw(topic, time_ns, encode_joint_state(stamp, names, position, velocity,
                                                          effort))

    def write_string(self, topic: str, time_ns: int, text: str, latched: bool = True) -> None:
        """Write a std_msgs/String (topic latched by default, as /robot_description)."""
        if topic not in self.topics:
            self.add_topic(topic, STRING, latched=latched)
        self.write(topic, time_ns, make_string(text, self.typestore))

    def write_clock(self, time_ns: int, topic: str = '/clock') -> None:
        """Write rosgraph_msgs/Clock carrying the log time itself (exact in ns)."""
        sec, nsec = divmod(int(time_ns), 1_000_000_000)
        types = self.typestore.types
        self.write(topic, time_ns, types[CLOCK](types['builtin_interfaces/msg/Time'](sec, nsec)))

    def close(self) -> None:
        """Finish the bag and move it into place (idempotent)."""
        writer, self._writer = self._writer, None
        if writer is None:
            return
        try:
            writer.close()
            for storage in (self._tmp / self.path.name).glob('*.mcap'):
                add_chunk_crcs(storage)
            self._commit()
        except BaseException as err:
            shutil.rmtree(self._tmp, ignore_errors=True)
            if isinstance(err, IdentificationError):
                raise
            if isinstance(err, Exception):
                raise IdentificationError(
                    f'cannot finish bag {str(self.path)!r}: {err}') from None
            raise

    def _commit(self) -> None:
        src = self._tmp / self.path.name
        old = None
        if self.path.exists() or self.path.is_symlink():
            if not self.overwrite:
                raise IdentificationError(
                    f'bag {str(self.path)!r} appeared while writing; not overwriting')
            old = Path(tempfile.mkdtemp(prefix=f'.{self.path.name}.', suffix='.old',
                                        dir=self.path.parent))
            self.path.rename(old / self.path.name)
        try:
            src.rename(self.path)
        except BaseException:
            if old is not None:
                (old / self.path.name).rename(self.path)
                old.rmdir()
            raise
        self._tmp.rmdir()
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def abort(self) -> None:
        """Discard everything written (idempotent)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.abort()
            except Exception:  # best effort: the directory goes anyway
                pass
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
