"""sensor_msgs/JointState on the wire: little-endian CDR decoded and encoded with struct and numpy.

The first stage of the path (bytes -> JointStateRecord), shared by the node's polled messages,
bag reading and bag writing. ``JointStateDecoder`` decodes one message about 5x faster than
the rosbags deserializer, which stays the reference and the fallback (big-endian data,
anything the fast path does not accept); ``decode_rows``/``decode_joint_states`` decode runs
of messages of one layout at once into a block record. The encoders write the same bytes as
rosbags' ``serialize_cdr``. Only public APIs of rosbags (typesys) are used.

Times: ``*_ns`` are integer nanoseconds, other times float seconds (``header.stamp``).
"""
from __future__ import annotations

import functools
import math
import struct
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import numpy as np

from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from identification_node.errors import IdentificationError
from identification_node.wire.records import JointStateRecord

JOINT_STATE = 'sensor_msgs/msg/JointState'
STRING = 'std_msgs/msg/String'
CLOCK = 'rosgraph_msgs/msg/Clock'
FLOAT64_MULTI_ARRAY = 'std_msgs/msg/Float64MultiArray'
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'
JOINT_TRAJECTORY = 'trajectory_msgs/msg/JointTrajectory'

__all__ = [
    'CLOCK', 'DIAGNOSTIC_ARRAY', 'FLOAT64_MULTI_ARRAY', 'JOINT_STATE', 'JOINT_TRAJECTORY',
    'STRING', 'JointStateDecoder', 'decode_joint_state', 'decode_joint_state_reference',
    'decode_joint_states', 'decode_rows', 'deserialize_cdr', 'encode_joint_state',
    'encode_joint_states', 'jazzy_typestore', 'sec_nsec',
]


@functools.lru_cache(maxsize=1)
def jazzy_typestore() -> Typestore:
    """Shared rosbags typestore of the ROS 2 Jazzy message types (do not register into it)."""
    return get_typestore(Stores.ROS2_JAZZY)


def sec_nsec(t: float) -> tuple[int, int]:
    """Split float seconds into (sec, nanosec) with 0 <= nanosec < 1e9."""
    if not math.isfinite(t):
        raise IdentificationError(f'time {t!r} is not finite')
    sec = math.floor(t)
    nsec = round((t - sec) * 1e9)
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return int(sec), int(nsec)


_HEAD = struct.Struct('<iII')  # header.stamp.sec, header.stamp.nanosec, len(frame_id)
_U32 = struct.Struct('<I')
_F8 = np.dtype('<f8')
_EMPTY = np.empty(0)
_EMPTY.flags.writeable = False

_MAX_BLOCK = 4096  # rows compared (and decoded) at once


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
        # the last block layout decode_rows saw: (row length, bytes that must match (mask),
        # their values, the arrays' (byte offset, count), names)
        self._layout: tuple[int, np.ndarray, np.ndarray, list[tuple[int, int]],
                            tuple[str, ...]] | None = None

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


def decode_rows(rows: np.ndarray, decoder: JointStateDecoder
                ) -> Iterator[tuple[int, int, JointStateRecord | IdentificationError]]:
    """JointState messages of equal length, rows (M, L) uint8, as (start, stop, record):
    runs of rows whose bytes agree everywhere but in the stamp and the array values share
    one layout and come as one block record (stamp_ns (M,) int64, (M, k) arrays); other rows
    one by one (a plain record), or the IdentificationError that says why a row cannot be
    decoded. The decoder keeps the last layout: rows of it are not parsed again."""
    k, L = 0, rows.shape[1]
    while k < len(rows):
        known = decoder._layout
        ahead = rows[k:k + _MAX_BLOCK]
        m = 0
        if known is not None and known[0] == L:
            same = (ahead[:, known[1]] == known[2]).all(axis=1)
            m = len(same) if same.all() else int(np.argmin(same))
        if m == 0:   # a new layout: the first row parsed (the reference decoder decides)
            raw = rows[k].tobytes()
            spans: list[tuple[int, int]] = []
            record: JointStateRecord | IdentificationError | None
            try:
                record = decoder._fast(raw, spans) if raw[:2] == b'\x00\x01' else None
            except (_Malformed, struct.error, ValueError, UnicodeDecodeError):
                record = None
            if record is None:
                try:
                    record = decoder(raw)
                except IdentificationError as err:
                    record = err
                yield k, k + 1, record
                k += 1
                continue
            mask = np.ones(L, dtype=bool)
            mask[4:12] = False  # header.stamp
            for offset, count in spans:
                mask[offset:offset + 8 * count] = False
            known = decoder._layout = (L, mask, rows[k, mask], spans, record.names)
            same = (ahead[1:, mask] == known[2]).all(axis=1)
            m = 1 + (len(same) if same.all() else int(np.argmin(same)))
        assert known is not None   # kept or just parsed
        *_, spans, names = known
        block = np.ascontiguousarray(ahead[:m])   # strided views of it, then copied
        stamps = (np.ndarray((m,), '<i4', block, 4, (L,)).astype(np.int64) * 1_000_000_000
                  + np.ndarray((m,), '<u4', block, 8, (L,)))
        arrays = [np.ndarray((m, c), _F8, block, o, (L, 8)).copy() if c else np.empty((m, 0))
                  for o, c in spans]
        if m == 1:
            yield k, k + 1, JointStateRecord(int(stamps[0]), names, *(a[0] for a in arrays))
        else:
            yield k, k + m, JointStateRecord(stamps, names, *arrays)
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


# ----------------------------------------------------------------------------------------
# Encoding
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
    sec, nsec = sec_nsec(stamp)
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
    n_position, n_velocity, n_effort = counts
    template = encode_joint_state(0.0, names, np.zeros(n_position), np.zeros(n_velocity),
                                  np.zeros(n_effort))
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
        if a is not None and count:
            rows[:, offset:offset + 8 * count] = a.view(np.uint8)
    return [row.tobytes() for row in rows]
