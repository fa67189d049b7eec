"""The node's estimate services, served by its service thread (service_requests.py) and
answered from the snapshot after them:

- ``~/reset`` (std_srvs/Trigger): forget the estimate and every buffered sample;
- ``~/freeze`` (std_srvs/SetBool): stop (true) or resume (false) updating the estimate;
- ``~/save`` (std_srvs/Trigger): write the estimate (estimate.yaml, identified.urdf) into
  ``output_directory``; the message lists the paths written;
- ``~/get_estimate`` (std_srvs/Trigger): the newest published estimate as JSON text.
"""
from __future__ import annotations

from typing import Any, Callable

from std_srvs.srv import SetBool, Trigger

from identification_node.ros.service_requests import (Outcome, RequestQueue, ServiceThread,
                                                      failed)

__all__ = ['EstimateServices']


class EstimateServices:
    """The services above on ``services``, handing their commands to ``requests``."""

    def __init__(self, services: ServiceThread, requests: RequestQueue):
        self.requests = requests
        services.add(Trigger, '~/reset', self._reset)
        services.add(SetBool, '~/freeze', self._freeze)
        services.add(Trigger, '~/save', self._save)
        services.add(Trigger, '~/get_estimate', self._get_estimate)

    @staticmethod
    def _answer(reply: Callable, response: Any, text: str) -> Callable[[Outcome], None]:
        def answer(outcome: Outcome) -> None:
            if outcome.error:
                reply(failed(response, outcome.error))
            else:
                response.success, response.message = True, text
                reply(response)
        return answer

    def _reset(self, _req: Trigger.Request, reply: Callable) -> None:
        self.requests.command('reset', None, self._answer(reply, Trigger.Response(),
                                                          'estimate reset'))

    def _freeze(self, req: SetBool.Request, reply: Callable) -> None:
        text = 'updates frozen' if req.data else 'updates resumed'
        self.requests.command('freeze', bool(req.data),
                              self._answer(reply, SetBool.Response(), text))

    def _save(self, _req: Trigger.Request, reply: Callable) -> None:
        def answer(outcome: Outcome) -> None:
            res = Trigger.Response()
            if outcome.error or outcome.saved is None:
                reply(failed(res, outcome.error or outcome.save_error))
            else:
                res.success, res.message = True, ' '.join(outcome.saved)
                reply(res)
        self.requests.command('save', None, answer)

    def _get_estimate(self, _req: Trigger.Request, reply: Callable) -> None:
        def answer(outcome: Outcome) -> None:
            self._answer(reply, Trigger.Response(), outcome.estimate)(outcome)
        self.requests.read(answer)
