"""Bag replay (identify_bag): reading joint states in blocks gives what message-by-message
reading gives, the same batches, rejections, checkpoints and estimate."""
from pathlib import Path

import numpy as np
import pytest

from identification_node.bags.reader import iter_joint_state_blocks, iter_joint_states

from identification_node.bags import feed
from identification_node.replay import stream as replay
from identification_node.settings import Settings, read_parameter_file

REPO = Path(__file__).resolve().parents[1]


def _one_by_one(reader, topic, on_malformed=None):
    for _, t_ns, record in iter_joint_states(reader, [topic], on_malformed):
        yield np.array([t_ns]), record


def _run(bag, settings, batch):
    outputs = []
    result = replay.identify_bag(bag, settings, settings.load_robot(), batch=batch,
                                 on_output=outputs.append)
    return result, outputs


@pytest.mark.parametrize('batch', [1000, 777])
def test_block_reading_equals_message_by_message(monkeypatch, batch):
    settings = Settings.from_dict(read_parameter_file(REPO / 'config' / 'crs_a465.yaml'))
    bag = REPO / 'bags' / 'crs_a465_fourier'
    calls = []
    blocks = iter_joint_state_blocks
    monkeypatch.setattr(feed, 'iter_joint_state_blocks',
                        lambda *a: calls.append(1) or blocks(*a))
    fast, fast_out = _run(bag, settings, batch)
    assert calls
    monkeypatch.setattr(feed, 'iter_joint_state_blocks', _one_by_one)
    slow, slow_out = _run(bag, settings, batch)
    assert fast.messages == slow.messages == 10001
    assert [len(o.stamps_ns) for o in fast_out] == [len(o.stamps_ns) for o in slow_out]
    for a, b in zip(fast_out, slow_out):
        np.testing.assert_array_equal(a.stamps_ns, b.stamps_ns)
        np.testing.assert_allclose(a.predicted, b.predicted, rtol=1e-9, atol=1e-9)
    p, q = fast.pipeline, slow.pipeline
    assert p.rejected == q.rejected and (p.received, p.used) == (q.received, q.used)
    assert [h.num_samples for h in fast.history] == [h.num_samples for h in slow.history]
    for a, b in zip(fast.history, slow.history):
        np.testing.assert_allclose(a.values, b.values, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(a.stddev, b.stddev, rtol=1e-7)
