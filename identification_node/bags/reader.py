"""rosbag2 (ROS 2 Jazzy) bag reading without rclpy, on top of `rosbags` and `mcap`.

Reading streams message by message (memory does not grow with the bag length); JointState
messages are decoded by ``wire.cdr``. ``iter_joint_state_blocks`` reads one JointState topic
of an indexed mcap bag a chunk at a time (the mcap library's reader: summary, chunk records,
decompression and checksum) and decodes runs of messages of one layout at once (another
~10x); it yields what ``iter_joint_states`` yields. Only public APIs of rosbags (Reader,
typesys) and mcap are used.

Times: ``*_ns`` are integer nanoseconds, other times float seconds; a bag's log time is
the receive time stored by the recorder, ``stamp`` the message's ``header.stamp``.
"""
from __future__ import annotations

import os
import struct
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

import numpy as np

from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from identification_node.bags.mcap_check import verify_chunks
from identification_node.errors import IdentificationError
from identification_node.safe_yaml import read_yaml
from identification_node.wire.cdr import (JOINT_STATE, STRING, JointStateDecoder, decode_rows,
                                          deserialize_cdr, jazzy_typestore)
from identification_node.wire.records import JointStateRecord

STORAGES = ('mcap', 'sqlite3')
_STORAGE_FILES = ('.mcap', '.db3')

__all__ = [
    'STORAGES', 'BagReader', 'open_bag', 'iter_joint_states', 'iter_joint_state_blocks',
    'iter_messages', 'iter_raw', 'read_string_topic', 'stamp_span',
]


def _storage_of(path: Path) -> str | None:
    """'sqlite3' or 'mcap' by the bag's storage files (None when it has neither)."""
    files = [path] if path.is_file() else (list(path.glob('*.db3')) + list(path.glob('*.mcap'))
                                           if path.is_dir() else [])
    suffixes = {f.suffix for f in files}
    return 'sqlite3' if '.db3' in suffixes else 'mcap' if '.mcap' in suffixes else None


def _reader_error(path: Path, err: BaseException) -> IdentificationError:
    """Translate a rosbags/storage exception into a readable IdentificationError (one
    line; the hint fits the bag's storage)."""
    text = ' '.join(str(err).split()) or type(err).__name__
    low = text.lower()
    storage = _storage_of(path)
    if isinstance(err, OSError):
        hint = 'cannot open a file of the bag'
    elif 'missing' in low and 'files' in low:
        hint = 'storage files listed in metadata.yaml are missing'
    elif storage == 'sqlite3' and not ('storage plugin' in low
                                       or 'unrecognized storage' in low):
        hint = ('the sqlite3 storage file is corrupt, truncated or not a rosbag2 database '
                '(recording interrupted? `sqlite3 IN.db3 .recover` may salvage it)')
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
        _check_metadata(path / 'metadata.yaml')
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


def _check_metadata(metadata: Path) -> dict:
    """The bag information of a rosbag2 metadata.yaml (safe_yaml's limits); one-line
    IdentificationError when it is not YAML or not rosbag2 metadata."""
    what = f'bag {str(metadata.parent)!r}: metadata.yaml'
    data = read_yaml(metadata, what)
    info = data.get('rosbag2_bagfile_information') if isinstance(data, dict) else None
    if not isinstance(info, dict):
        raise IdentificationError(f'{what} holds no rosbag2_bagfile_information mapping '
                                  '(restore it with `ros2 bag reindex`)')
    return info


class BagReader:
    """Open rosbag2 bag (directory with metadata.yaml, or a lone .mcap/.db3 file).

    Opens on construction (errors surface as IdentificationError); use as a context manager
    or call close(). Attributes: path, topics {topic: msgtype}, topic_counts {topic: n},
    message_count, start_ns/end_ns (first/last log time), start_time/end_time [s], duration.
    """

    def __init__(self, path: str | os.PathLike, *, allow_empty: bool = False) -> None:
        self.path = Path(path)
        self._files: list[BinaryIO] = []
        target = _storage_target(self.path)
        try:
            self._reader: Reader | None = Reader(target)
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
        assert reader is not None  # opened by __init__
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

    def raw_messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None
                     ) -> Iterator[tuple[str, str, int, bytes]]:
        """Yield (topic, msgtype, log_time_ns, cdr_bytes) in log-time order (all if None),
        from log time ``start_ns`` on when given."""
        if self._reader is None:
            raise IdentificationError(f'bag {str(self.path)!r} is closed')
        wanted = None if topics is None else set(self.check_topics(topics))
        conns = [c for c in self._connections if wanted is None or c.topic in wanted]
        if not conns:
            return
        try:
            for conn, t_ns, raw in self._reader.messages(conns, start=start_ns):
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


def open_bag(path: str | os.PathLike, *, allow_empty: bool = False) -> BagReader:
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


# on_malformed(topic, log time ns, error): told of a message that cannot be decoded, which
# is then skipped; without it such a message raises IdentificationError.
Malformed = Callable[[str, int, IdentificationError], None]


def _undecodable(topic: str, t_ns: int, err: IdentificationError,
                 on_malformed: Malformed | None) -> None:
    """Tell ``on_malformed`` of an undecodable message, or raise the error naming it."""
    if on_malformed is None:
        raise IdentificationError(f'topic {topic!r} at log time {t_ns} ns: {err}') from None
    on_malformed(topic, t_ns, err)


def iter_joint_states(reader: BagReader, topics: str | Iterable[str],
                      on_malformed: Malformed | None = None
                      ) -> Iterator[tuple[str, int, JointStateRecord]]:
    """Yield (topic, log time ns, record) in log-time order across JointState topics (an
    undecodable message: see Malformed)."""
    topics = reader.check_topics(topics, JOINT_STATE)
    decoders = {t: JointStateDecoder() for t in topics}
    for topic, _, t_ns, raw in reader.raw_messages(topics):
        try:
            record = decoders[topic](raw)
        except IdentificationError as err:
            _undecodable(topic, t_ns, err, on_malformed)
            continue
        yield topic, t_ns, record


def stamp_span(reader: BagReader, topic: str) -> tuple[int, int] | None:
    """Header stamps (int ns) of the first and the last decodable message of the JointState
    ``topic`` in log-time order, or None when it has none; the last found reading back from
    the bag's end over spans of log time growing tenfold from 0.1 s."""
    decoder = JointStateDecoder()

    def stamps(start_ns: int | None = None) -> Iterator[int]:
        for _, _, _, raw in reader.raw_messages([topic], start_ns):
            try:
                yield int(decoder(raw).stamp_ns)
            except IdentificationError:
                continue
    first = next(stamps(), None)
    if first is None:
        return None
    span = 10**8
    while True:
        after = reader.end_ns - span
        last = None
        for last in stamps(after if after > reader.start_ns else None):
            pass
        if last is not None:
            return first, last
        span *= 10


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
# Block reading: runs of same-layout JointState messages from indexed mcap chunks
# ----------------------------------------------------------------------------------------

_RECORD = struct.Struct('<BQ')  # mcap record head: opcode, body length
_MESSAGE = 0x05                 # mcap message record; its body: channel id (u16), sequence
_MESSAGE_HEAD = 22              # (u32), log time (u64), publish time (u64), then the data


def iter_joint_state_blocks(reader: BagReader, topic: str,
                            on_malformed: Malformed | None = None
                            ) -> Iterator[tuple[np.ndarray, JointStateRecord]]:
    """The messages of ``iter_joint_states(reader, [topic])``, in the same order with the
    same values and errors, as (log times ns (M,), record). Consecutive messages sharing their
    layout (frame_id, names, array lengths) come as one block record: stamp_ns (M,) int64 and
    (M, k) arrays, decoded at once from the bag's indexed mcap chunks (one chunk in memory at a
    time). Other messages come one by one (M = 1, a plain record), and so do all messages of
    bags this does not handle (sqlite3, unindexed or time-overlapping chunks, per-message
    compression). An undecodable message: see Malformed."""
    reader.check_topics([topic], JOINT_STATE)
    storages = _mcap_storages(reader, topic)
    if storages is None:
        for _, t_ns, record in iter_joint_states(reader, [topic], on_malformed):
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
            yield from _chunk_blocks(buf, *found, ids, chunk, decoder, topic, on_malformed)


def _mcap_files(reader: BagReader) -> list[Path] | None:
    """The bag's storage files when they are plain mcap (rosbag2 metadata.yaml, or a lone
    .mcap file), else None."""
    path = reader.path
    if path.is_file():
        return [path] if path.suffix == '.mcap' else None
    if not (path / 'metadata.yaml').is_file():
        lone = _storage_target(path)
        return [lone] if lone.suffix == '.mcap' else None
    info = _check_metadata(path / 'metadata.yaml')
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
                  decoder: JointStateDecoder, topic: str, on_malformed: Malformed | None
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
        yield from _same_layout_blocks(rows, log[first:stop], decoder, topic, on_malformed)


def _same_layout_blocks(rows: np.ndarray, log: np.ndarray, decoder: JointStateDecoder,
                        topic: str, on_malformed: Malformed | None = None
                        ) -> Iterator[tuple[np.ndarray, JointStateRecord]]:
    """The decoded blocks of rows (M, L) of a bag's topic (an undecodable message: see
    Malformed)."""
    for start, stop, record in decode_rows(rows, decoder):
        if isinstance(record, IdentificationError):
            _undecodable(topic, int(log[start]), record, on_malformed)
            continue
        yield log[start:stop], record
