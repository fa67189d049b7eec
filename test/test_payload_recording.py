"""The real Kinova Gen3 recording of ../shared/data (bench/recordings.py) carries an
undocumented end-effector load: identified with the URDF as the arm (``identify BAG
--payload``, the shipped defaults), the payload is reported with a finite positive mass and
its stddev (bench/bench_payload.py --recording has the figures)."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'bench'))
from corpus import run_identify  # noqa: E402
from recordings import data_dir, kinova_bags  # noqa: E402


@pytest.mark.skipif(not (data_dir() / 'kinova_gen3').is_dir(), reason='no ../shared/data')
def test_kinova_gen3_load_is_reported_with_its_stddev(tmp_path):
    train, _ = kinova_bags(tmp_path)
    code, doc = run_identify([str(train), '--payload'])
    assert code == 0
    [segment] = doc['payload_changes']          # no change over the run
    fitted = segment['payload']['fitted']
    mass, sd = fitted['mass'], fitted['stddev']['mass']
    assert math.isfinite(mass) and mass > 0 and math.isfinite(sd) and 0 < sd < mass / 5
    assert all(math.isfinite(c) for c in fitted['com'] + fitted['stddev']['com'])
    # the URDF's arm lacks the joints' friction: said, not silently
    assert any('identify the arm first' in w for w in doc['payload_warnings'])
