"""The node's services on a thread of their own, answered from published snapshots.

:class:`ServiceThread` takes the requests of its services itself (they sit in a PolledGroup,
which no executor dispatches) on a daemon thread, in the order they were sent (a poll sweeps
the services until all are empty and sorts what it took by source timestamp), and sends every
response from that same thread. A handler may answer later: it gets a ``reply`` callable
that any thread may call.

:class:`RequestQueue` is what the handlers hand work to, so that no service waits on the
processing thread's work (nor on its lock): commands (reset, freeze, save, payload) are
queued, numbered in arrival order, for the processing thread to apply at the start of its
next run, in order (a run of several resets applies once, and coalesced saves write once);
the snapshot taken after them (estimate, its constrained solve, the saved files) answers
every request up to that number at once, in order. Commands that no earlier read or save
waits before are answered as soon as they are applied (their answer does not depend on the
solve, which a busy machine may keep waiting). A read (``~/get_estimate``) is answered at
once from the newest snapshot, unless a command sent before it is still queued: then from
the first snapshot after it. A snapshot that fails answers the requests it was for with the
reason.
"""
from __future__ import annotations

import contextlib
import re
import threading
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from identification_node.ros.conversions import PolledGroup

# Requests the middleware holds per service until the thread takes them (rclpy's default
# is 10: a burst of calls beyond it was dropped without a word, its callers waiting forever).
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                         reliability=ReliabilityPolicy.RELIABLE)
POLL_ACTIVE = 0.002     # s between polls while requests come
POLL_IDLE = 0.02        # s between polls once none came for a while
MAX_SWEEPS = 8          # sweeps over the services per poll while requests keep coming
# rmw_fastrtps refuses a response while the caller's reply reader is not matched yet (a new
# client's first call, discovery slow on a busy machine): it is sent again for this long.
RESEND_FOR = 10.0
# rclpy does not raise when the middleware refuses a response (RCL_RET_TIMEOUT): it warns and
# drops it. Raised instead, for the calls of this module only (the warning is attributed to
# the frame that called the binding), so that it is sent again.
_REFUSED = ('error', re.compile(r'failed to send response \(timeout\)', re.I), RuntimeWarning,
            re.compile(re.escape(__name__) + r'\Z'), 0)
Reply = Callable[[Any], None]


def _never(_request: Any, response: Any) -> Any:   # pragma: no cover - never dispatched
    return response


def _requests(srv) -> Iterator[tuple]:
    """(request, header) of everything waiting at service ``srv``, in the order received."""
    with srv.handle:
        while True:
            request, header = srv.handle.service_take_request(srv.srv_type.Request)
            if header is None:
                return
            yield request, header


class ServiceThread:
    """Services of ``node`` served by a thread of their own (see the module doc); ``on_error``
    gets a handler's exception (the request is then answered with ``failed(response, text)``
    where the response has a place for it)."""

    def __init__(self, node: Node, on_error: Callable[[str, BaseException], None],
                 name: str = 'identification_services') -> None:
        self.node, self._on_error, self._name = node, on_error, name
        self._group = PolledGroup()
        self._services: list[tuple[Any, Callable[[Any, Reply], None], str]] = []
        self._outbox: list[tuple] = []    # (service, response, header, first try), in order
        self._outbox_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.answered = 0
        self._thread: threading.Thread | None = None

    def add(self, srv_type: Any, name: str, handler: Callable[[Any, Reply], None]) -> None:
        """Serve ``name``: ``handler(request, reply)`` calls ``reply(response)`` once, now or
        later, from any thread."""
        srv = self.node.create_service(srv_type, name, _never, qos_profile=SERVICE_QOS,
                                       callback_group=self._group)
        self._services.append((srv, handler, name))

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()

    def _reply(self, srv: Any, header: Any) -> Reply:
        done: list[bool] = []

        def reply(response: Any) -> None:
            if done:
                return
            done.append(True)
            with self._outbox_lock:
                self._outbox.append((srv, response, header, None))
            self._wake.set()
        return reply

    def _run(self) -> None:
        idle = 0
        while not self._stop.is_set():
            taken = self._take()
            for _stamp, srv, handler, name, request, header in taken:
                reply = self._reply(srv, header)
                try:
                    handler(request, reply)
                except Exception as exc:   # noqa: BLE001 - counted, answered, never raised
                    self._on_error(name, exc)
                    response = srv.srv_type.Response()
                    reply(failed(response, f'{name} failed: {type(exc).__name__}: {exc}'))
            sent = self._send()
            idle = 0 if taken or sent else idle + 1
            self._wake.wait(POLL_ACTIVE if idle < 50 else POLL_IDLE)
            self._wake.clear()

    def _take(self) -> list[tuple]:
        """The requests of every service, sorted by source timestamp: swept until a sweep
        finds every service empty (at most MAX_SWEEPS), so that a request taken comes with
        those sent before it to services swept earlier. One sweep could take a save and leave
        the reset sent before it, which arrived while the thread was between the two, for
        the next poll."""
        taken: list[tuple] = []
        for _ in range(MAX_SWEEPS):
            count = len(taken)
            for srv, handler, name in self._services:
                with contextlib.suppress(Exception):   # a destroyed service (shutdown)
                    taken += ((header.source_timestamp, srv, handler, name, request, header)
                              for request, header in _requests(srv))
            if len(taken) == count:
                break
        taken.sort(key=lambda t: t[0])   # stable: one service's requests stay in order
        return taken

    def _send(self) -> int:
        with self._outbox_lock:
            out, self._outbox = self._outbox, []
        again = []
        held: set[int] = set()    # services with a response to send again: the later wait
        now = time.monotonic()
        for srv, response, header, first in out:
            if id(srv) in held:
                again.append((srv, response, header, first))
                continue
            try:
                _send_response(srv, response, header)
                self.answered += 1
            except Exception as exc:   # noqa: BLE001 - not matched yet, vanished, shut down
                if first is None or now - first < RESEND_FOR:
                    again.append((srv, response, header, now if first is None else first))
                    held.add(id(srv))
                else:
                    self._on_error('send_response', exc)
        if again:
            with self._outbox_lock:
                self._outbox[:0] = again
        return len(out) - len(again)


def _send_response(srv: Any, response: Any, header: Any) -> None:
    """``srv.send_response``, but raising RuntimeWarning when the middleware refuses the
    response (rclpy only warns)."""
    if warnings.filters[:1] != [_REFUSED]:  # first, whatever was put before it since
        warnings.filterwarnings('error', _REFUSED[1].pattern, _REFUSED[2], _REFUSED[3].pattern)
    if not isinstance(response, srv.srv_type.Response):
        raise TypeError(f'a {srv.srv_type.__name__} response expected, got '
                        f'{type(response).__name__}')
    with srv.handle:
        srv.handle.service_send_response(response, header.request_id)


def failed(response: Any, text: str) -> Any:
    """``response`` marked failed with ``text`` (std_srvs' success/message, or
    rcl_interfaces/SetParameters' results)."""
    if hasattr(response, 'success'):
        response.success, response.message = False, text
    elif hasattr(response, 'results'):
        from rcl_interfaces.msg import SetParametersResult
        response.results = [SetParametersResult(successful=False, reason=text)]
    return response


@dataclass
class Outcome:
    """What a snapshot gives the requests it answers: the estimate as the JSON text of
    ``~/get_estimate``, the paths saved (None: no save was asked or it failed), or the
    reason it failed."""
    estimate: str = ''
    saved: list[str] | None = None
    save_error: str = ''
    error: str = ''


@dataclass
class Snapshot:
    """The pipeline's state after command ``seq``, taken on the processing thread for the
    worker: the estimate (pipeline.EstimateReport), the constrained solve's equations (None:
    consistency off) and, when it is to be ``save``d, the covariance, rejection counts and
    payload; ``error``: why it could not be taken."""
    seq: int
    save: bool
    estimate: Any = None
    equations: tuple | None = None
    covariance: Any = None
    rejected: dict = field(default_factory=dict)
    payload: Any = None
    error: str = ''


@dataclass
class _Waiter:
    seq: int
    kind: str                       # 'read', 'command', 'save'
    answer: Callable[[Outcome], None]


@dataclass
class Commands:
    """The commands the processing thread takes in one go: ``items`` ((number, kind,
    argument), in order; saves included) and whether a snapshot is due after them anyway (a
    refresh or a read asked for one). See :meth:`snapshots`."""
    items: list[tuple[int, str, Any]] = field(default_factory=list)
    seq: int = 0
    wanted: bool = False

    def snapshots(self) -> list[tuple[list[tuple[str, Any]], int, bool]]:
        """The commands cut where a snapshot must be taken: (commands to apply first, the
        number the snapshot answers up to, whether it is saved). A run of saves is one
        snapshot, saved once; a snapshot follows the last command."""
        out, pending = [], []
        for k, (seq, kind, arg) in enumerate(self.items):
            if kind != 'save':
                pending.append((kind, arg))
            elif k + 1 == len(self.items) or self.items[k + 1][1] != 'save':
                out.append((pending, seq, True))
                pending = []
        if pending or self.wanted or not out:
            out.append((pending, self.seq, False))
        return out


class RequestQueue:
    """Commands for the processing thread and answers from snapshots (see the module doc).
    Thread-safe; never blocks on anything but its own short lock."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._seq = 0                 # number of the last command queued
        self._items: list[tuple[int, str, Any]] = []
        self._wanted = True           # a snapshot is due (the first one: at once)
        self._waiting: list[_Waiter] = []
        self._seq_done = -1           # the newest snapshot answered commands up to here
        self._latest = Outcome(error='no estimate yet')
        self.on_request: Callable[[], None] = lambda: None   # a command or read now waits

    def command(self, kind: str, argument: Any, answer: Callable[[Outcome], None]) -> None:
        """Queue command ``kind`` (``'save'``: answered once saved); ``answer(outcome)`` is
        called from the snapshot that follows it."""
        with self._lock:
            self._seq += 1
            self._items.append((self._seq, kind, argument))
            self._waiting.append(_Waiter(self._seq, 'save' if kind == 'save' else 'command',
                                         answer))
        self.on_request()

    def read(self, answer: Callable[[Outcome], None]) -> None:
        """``answer(outcome)`` with the newest snapshot, now unless a command before this
        read still waits for its own."""
        with self._lock:
            waits = self._seq_done < self._seq or self._seq_done < 0
            if waits:
                self._waiting.append(_Waiter(self._seq, 'read', answer))
                self._wanted = True
            latest = self._latest
        if waits:
            self.on_request()
        else:
            answer(latest)

    def want_snapshot(self) -> None:
        """Ask the processing thread for a snapshot at its next run (the periodic refresh)."""
        self._wanted = True

    def take(self) -> Commands | None:
        """The queued commands, for the processing thread; None when no snapshot is due."""
        with self._lock:
            if not self._items and not self._wanted:
                return None
            taken = Commands(self._items, self._seq, self._wanted)
            self._items, self._wanted = [], False
        return taken

    def applied(self, seq: int) -> None:
        """The commands up to ``seq`` are applied and their snapshot taken: answer the
        commands among the first requests waiting, up to the first read or save (which need
        the snapshot's estimate or files), so that answers stay in order."""
        with self._lock:
            k = 0
            while (k < len(self._waiting) and self._waiting[k].kind == 'command'
                   and self._waiting[k].seq <= seq):
                k += 1
            due, self._waiting = self._waiting[:k], self._waiting[k:]
        for w in due:
            w.answer(Outcome())

    def answer(self, seq: int, outcome: Outcome) -> None:
        """A snapshot taken after command ``seq``: answer every request it covers, in order."""
        with self._lock:
            if seq >= self._seq_done:
                self._seq_done, self._latest = seq, outcome
            due = [w for w in self._waiting if w.seq <= seq]
            self._waiting = [w for w in self._waiting if w.seq > seq]
        for w in due:
            w.answer(outcome)

    @property
    def waiting(self) -> int:
        with self._lock:
            return len(self._waiting)
