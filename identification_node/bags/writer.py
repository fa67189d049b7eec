"""rosbag2 (ROS 2 Jazzy) bag writing without rclpy (rosbags' Writer), and the builders of the
messages the package writes (rosbags message objects from SI values).

Writing goes into a hidden temporary sibling directory that is renamed into place on a
successful close, so a bag path either holds a complete bag or nothing.

Times: ``time_ns`` are bag log times in integer nanoseconds, ``stamp`` is ``header.stamp`` in
float seconds.
"""
from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Final

import numpy as np

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability
from rosbags.interfaces import QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys.store import Typestore

from identification_node.bags.mcap_check import add_chunk_crcs
from identification_node.bags.reader import STORAGES
from identification_node.error_lines import os_error_text
from identification_node.errors import IdentificationError
from identification_node.wire.cdr import (CLOCK, DIAGNOSTIC_ARRAY, FLOAT64_MULTI_ARRAY,
                                          JOINT_STATE, JOINT_TRAJECTORY, STRING,
                                          encode_joint_state, jazzy_typestore, sec_nsec)

_BAG_VERSION: Final = 9  # rosbag2 metadata version written by Jazzy

__all__ = [
    'BagWriter', 'check_replaceable', 'not_a_bag', 'make_time', 'make_duration', 'make_header',
    'make_joint_state', 'make_string', 'make_clock', 'make_float64_multi_array',
    'make_diagnostic_array', 'make_joint_trajectory',
]


# Files a bag directory holds besides its storage: rosbag2's metadata and the simulated
# arm's truth (cli/simulate.py); sqlite3 storage may leave its journal files beside it.
BAG_DIRECTORY_FILES = ('metadata.yaml', 'true_parameters.yaml')
_STORAGE_SUFFIXES = ('.mcap', '.db3', '.db3-wal', '.db3-shm', '.db3-journal')


def not_a_bag(path: str | Path) -> str | None:
    """Why the existing ``path`` is not a bag that may be replaced (a regular file, a link,
    a directory without metadata.yaml or storage files, or holding any other file), or None
    when it is one (or does not exist)."""
    path = Path(path)
    if path.is_symlink():
        return 'a symbolic link'
    if not path.exists():
        return None
    if not path.is_dir():
        return 'not a directory'
    entries = sorted(path.iterdir())
    other = [p.name for p in entries if not p.is_file() or p.is_symlink() or not (
        p.name in BAG_DIRECTORY_FILES or p.name.endswith(_STORAGE_SUFFIXES))]
    if other:
        return f'a directory holding {", ".join(other[:3])}{", ..." if len(other) > 3 else ""}'
    if not any(p.name == 'metadata.yaml' or p.name.endswith(('.mcap', '.db3'))
               for p in entries):
        return 'a directory without metadata.yaml or storage files'
    return None


def check_replaceable(path: str | Path, what: str = 'bag') -> None:
    """IdentificationError when ``path`` exists and is not a bag (``not_a_bag``): writers
    replace (``--overwrite``) only what they wrote themselves."""
    reason = not_a_bag(path)
    if reason is not None:
        raise IdentificationError(f'{what} {str(path)!r} exists and is not a bag ({reason}); '
                                  'not replacing it')


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
        check_replaceable(self.path)
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
            raise IdentificationError(f'cannot create bag {str(self.path)!r}: '
                                      f'{os_error_text(err)}') from None
        try:
            plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
            self._writer = Writer(self._tmp / self.path.name, version=_BAG_VERSION,
                                  storage_plugin=plugin)
            self._writer.open()
        except Exception as err:
            self.abort()
            raise IdentificationError(f'cannot create bag {str(self.path)!r}: '
                                      f'{os_error_text(err) if isinstance(err, OSError) else err}'
                                      ) from None

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
        try:
            writer.write(conn, time_ns, cdr)
        except OSError as err:   # a full disk while writing names no file: name the bag
            raise IdentificationError(f'cannot write bag {str(self.path)!r}: '
                                      f'{os_error_text(err)}') from None
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
                    f'cannot finish bag {str(self.path)!r}: '
                    f'{os_error_text(err) if isinstance(err, OSError) else err}') from None
            raise

    def _commit(self) -> None:
        src = self._tmp / self.path.name
        old = None
        if self.path.exists() or self.path.is_symlink():
            if not self.overwrite:
                raise IdentificationError(
                    f'bag {str(self.path)!r} appeared while writing; not overwriting')
            check_replaceable(self.path)
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


# ----------------------------------------------------------------------------------------
# Message construction
# ----------------------------------------------------------------------------------------

def make_time(t: float, typestore: Typestore | None = None) -> Any:
    """builtin_interfaces/Time from float seconds."""
    sec, nsec = sec_nsec(t)
    return (typestore or jazzy_typestore()).types['builtin_interfaces/msg/Time'](sec, nsec)


def make_duration(t: float, typestore: Typestore | None = None) -> Any:
    """builtin_interfaces/Duration from float seconds."""
    sec, nsec = sec_nsec(t)
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
