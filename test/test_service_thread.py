"""ServiceThread's sending, without ROS traffic: a response the middleware refuses is sent
again. rclpy does not raise then: its binding warns (RuntimeWarning 'failed to send response
(timeout)', attributed to the calling frame) and drops the response; the fake handle below
does the same."""
import warnings
from types import SimpleNamespace

from std_srvs.srv import Trigger

from identification_node.ros.service_requests import ServiceThread

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
