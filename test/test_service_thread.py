"""The service thread's queue and sending, without ROS traffic. RequestQueue answers in
order. ServiceThread sends again a response the middleware refuses: rclpy does not raise
then (its binding warns RuntimeWarning 'failed to send response (timeout)', attributed to the
calling frame, and drops the response); the fake handle below does the same."""
import warnings
from types import SimpleNamespace

from std_srvs.srv import Trigger

from identification_node.ros.service_requests import (MAX_SWEEPS, Outcome, RequestQueue,
                                                      ServiceThread)

REFUSAL = 'failed to send response (timeout): client will not receive response'


class RefusingHandle:
    """An rclpy service handle whose middleware refuses the first ``refusals`` responses."""

    def __init__(self, refusals: int) -> None:
        self.refusals, self.sent = refusals, []

    def __enter__(self) -> 'RefusingHandle':
        return self

    def __exit__(self, *exc) -> bool:
        return False

    def service_send_response(self, response, request_id) -> None:
        if self.refusals:
            self.refusals -= 1
            # as rclpy's binding: the caller's frame gets the warning, nothing is raised
            warnings.warn(REFUSAL, RuntimeWarning, stacklevel=2)
            return
        self.sent.append((response, request_id))


def test_a_refused_response_is_sent_again():
    errors = []
    thread = ServiceThread(None, lambda name, exc: errors.append((name, exc)))
    srv = SimpleNamespace(srv_type=Trigger, handle=RefusingHandle(refusals=2))
    response = Trigger.Response(success=True, message='done')
    thread._reply(srv, SimpleNamespace(request_id=7))(response)
    assert thread._send() == 0 and thread._send() == 0     # refused twice: kept
    assert thread._send() == 1
    assert srv.handle.sent == [(response, 7)] and thread.answered == 1 and not errors
    assert thread._send() == 0                              # sent once only


def test_responses_after_a_refused_one_wait_for_it():
    """A service's answers leave in the order they were given: those after a refused one are
    held until it is sent (a new client's first answers are refused until it is matched)."""
    thread = ServiceThread(None, lambda name, exc: None)
    srv = SimpleNamespace(srv_type=Trigger, handle=RefusingHandle(refusals=1))
    other = SimpleNamespace(srv_type=Trigger, handle=RefusingHandle(refusals=0))
    for k in range(3):
        thread._reply(srv, SimpleNamespace(request_id=k))(Trigger.Response(message=str(k)))
    thread._reply(other, SimpleNamespace(request_id=9))(Trigger.Response())
    assert thread._send() == 1 and srv.handle.sent == []    # another service is not held
    assert thread._send() == 3
    assert [(r.message, i) for r, i in srv.handle.sent] == [('0', 0), ('1', 1), ('2', 2)]


def test_other_warnings_are_left_alone():
    """The refusal is an error only where ServiceThread sends: elsewhere it stays a warning."""
    handle = RefusingHandle(refusals=1)
    thread = ServiceThread(None, lambda name, exc: None)
    srv = SimpleNamespace(srv_type=Trigger, handle=RefusingHandle(refusals=0))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter('always')
        thread._reply(srv, SimpleNamespace(request_id=1))(Trigger.Response())
        assert thread._send() == 1      # its filter goes first
        handle.service_send_response(Trigger.Response(), 2)     # called from here
    assert [str(w.message) for w in seen] == [REFUSAL]


def test_commands_are_answered_once_applied_reads_and_saves_by_their_snapshot():
    """A command's answer needs no solve: it goes out once applied, unless a read or save
    sent before it still waits for its snapshot (answers stay in order)."""
    queue, log = RequestQueue(), []

    def record(name):
        return lambda outcome: log.append((name, outcome.error or outcome.estimate))

    queue.command('reset', None, record('reset 1'))        # 1
    queue.command('save', None, record('save 2'))          # 2
    queue.command('reset', None, record('reset 3'))        # 3
    queue.read(record('read after 3'))
    queue.command('freeze', True, record('freeze 4'))      # 4
    queue.applied(1)
    assert log == [('reset 1', '')]
    queue.applied(3)                 # the save waits for its snapshot, so does all after it
    assert log == [('reset 1', '')]
    queue.answer(2, Outcome(estimate='after 2'))
    assert log[1:] == [('save 2', 'after 2')]
    queue.applied(4)                 # reset 3 goes; the read waits for the snapshot after 3
    assert log[2:] == [('reset 3', '')]
    queue.answer(4, Outcome(estimate='after 4'))
    assert log[3:] == [('read after 3', 'after 4'), ('freeze 4', 'after 4')]
    queue.answer(4, Outcome(estimate='again'))           # nothing is answered twice
    queue.applied(4)
    assert len(log) == 5 and queue.waiting == 0


def test_a_request_that_waits_wakes_the_processing_thread():
    """Commands and reads that wait for a snapshot call ``on_request`` (the node's processing
    thread then runs at once, whatever its period); a read answered at once does not."""
    queue, log, woken = RequestQueue(), [], []
    queue.on_request = lambda: woken.append(1)
    queue.read(log.append)                        # no snapshot yet: waits
    assert len(woken) == 1 and log == []
    queue.answer(0, Outcome(estimate='first'))
    queue.read(log.append)                        # answered from the snapshot
    assert len(woken) == 1 and [o.estimate for o in log] == ['first', 'first']
    queue.command('reset', None, log.append)
    assert len(woken) == 2


class QueuedHandle:
    """An rclpy service handle whose requests are what the test put in ``queue``;
    ``on_take()`` runs before each take (the middleware delivering meanwhile)."""

    def __init__(self) -> None:
        self.queue: list = []
        self.on_take = lambda: None

    def __enter__(self) -> 'QueuedHandle':
        return self

    def __exit__(self, *exc) -> bool:
        return False

    def service_take_request(self, request_type):
        self.on_take()
        return self.queue.pop(0) if self.queue else (None, None)


def _services(thread, *names):
    srvs = [SimpleNamespace(srv_type=Trigger, handle=QueuedHandle()) for _ in names]
    thread._services = [(srv, None, name) for srv, name in zip(srvs, names)]
    return srvs


def _request(stamp):
    return Trigger.Request(), SimpleNamespace(source_timestamp=stamp)


def test_a_request_is_taken_with_those_sent_before_it_to_services_swept_earlier():
    """The thread takes each service's requests in turn. A burst of (save, reset) pairs that
    arrives between the two (the thread paused: another thread held the GIL) left the resets
    for the next poll, and the saves went first: a frozen node's save after a reset wrote
    the estimate before it. Every request taken comes with those sent before it."""
    thread = ServiceThread(None, lambda name, exc: None)
    reset, save = _services(thread, 'reset', 'save')

    def burst():   # arrives once the reset queue was found empty
        save.handle.on_take = lambda: None
        for k in range(6):     # save 0, reset 1, save 2, ...: stamps in the order sent
            (reset if k % 2 else save).handle.queue.append(_request(k))
    save.handle.on_take = burst
    taken = thread._take()
    assert [(t[3], t[0]) for t in taken] == [('save', 0), ('reset', 1), ('save', 2),
                                             ('reset', 3), ('save', 4), ('reset', 5)]
    assert thread._take() == []


def test_requests_that_never_stop_coming_end_the_poll():
    """A request arrives for one service at every sweep over the others: the poll ends
    after MAX_SWEEPS sweeps, in stamp order, what it took of the others among it."""
    thread = ServiceThread(None, lambda name, exc: None)
    busy, other = _services(thread, 'busy', 'other')
    stamps = iter(range(1, 100))
    other.handle.queue.append(_request(0))
    other.handle.on_take = lambda: busy.handle.queue.append(_request(next(stamps)))
    taken = thread._take()
    assert [t[0] for t in taken] == list(range(MAX_SWEEPS + 1))
    assert taken[0][3] == 'other' and {t[3] for t in taken[1:]} == {'busy'}
