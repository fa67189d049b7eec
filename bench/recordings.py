"""Real-arm recordings of ../shared/data as rosbag2 bags, identified with the defaults.

``joint_state_bag`` writes sampled arrays (t s, q rad, qd rad/s or none, tau N m) as
/joint_states with /robot_description through the package's BagWriter: what ``identify``
reads. The recordings (see their READMEs):

- ``tx40``: Staubli TX40, 5 kHz, 9 s, joint side (tx40_joint_side.npz: positions and torques,
  no velocity; the coupled wrist's extra terms are not modelled). Held out: split in time,
  training 0-6 s, held out 6-9 s.
- ``kinova_gen3``: Kinova Gen3, 1 kHz, joint torque sensors (TorqueSm) with measured position
  and velocity; training opti_traj_testing1 (4.7 s), held out opti_traj_testing2 (2.3 s),
  another optimised motion recorded later. It carries an undocumented end-effector load.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from identification_node.bags.writer import BagWriter  # noqa: E402
from identification_node.wire.cdr import JOINT_STATE  # noqa: E402

T0_NS = 1_700_000_000_000_000_000
RECORDINGS = ('tx40', 'kinova_gen3')
TX40_SPLIT = 6.0    # s: training before, held out after


def data_dir() -> Path:
    """../shared/data (the environment variable IDENTIFICATION_DATA overrides it)."""
    import os

    return Path(os.environ.get('IDENTIFICATION_DATA', '/work/shared/data'))


def joint_state_bag(path: str | Path, t: np.ndarray, names: Sequence[str], q: np.ndarray,
                    qd: np.ndarray | None, tau: np.ndarray, description: str) -> Path:
    """Samples as a rosbag2 (mcap) bag at ``path``: /joint_states stamped at T0 + t (s) and a
    latched /robot_description. ``qd`` None: the messages carry no velocity."""
    t, q, tau = np.asarray(t, dtype=float), np.asarray(q, dtype=float), np.asarray(tau, float)
    if not (q.shape == tau.shape == (len(t), len(names))):
        raise ValueError(f'q {q.shape} and tau {tau.shape} must be ({len(t)}, {len(names)})')
    ns = T0_NS + np.round((t - t[0]) * 1e9).astype(np.int64)
    with BagWriter(path, 'mcap', overwrite=True) as bag:
        bag.add_topic('/joint_states', JOINT_STATE)
        bag.write_string('/robot_description', int(ns[0]), description)
        for k, stamp in enumerate(ns.tolist()):
            bag.write_joint_state('/joint_states', stamp, stamp * 1e-9, names, q[k],
                                  () if qd is None else qd[k], tau[k])
    return Path(path)


def tx40_bags(out: Path) -> tuple[Path, Path]:
    """(training, held-out) bags of the TX40 run, split at TX40_SPLIT s."""
    root = data_dir() / 'staubli_tx40'
    z = np.load(root / 'tx40_joint_side.npz')
    t, q, tau = z['t'], z['q'], z['tau']
    names = [str(n) for n in z['joint_names']]
    urdf = (root / 'tx40_mdh_modified.urdf').read_text()
    first = t < TX40_SPLIT
    return tuple(joint_state_bag(Path(out) / label, t[sel], names, q[sel], None, tau[sel], urdf)
                 for label, sel in (('tx40_train', first), ('tx40_heldout', ~first)))


def kinova_columns(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t s, position, velocity, joint-sensor torque (N, 7)) of one Kinova Gen3 CSV."""
    D = np.genfromtxt(path, delimiter=',', names=True)

    def block(prefix: str) -> np.ndarray:
        return np.stack([D[f'{prefix}{i}'] for i in range(1, 8)], axis=1)
    return D['Time'] * 1e-3, block('Position'), block('Velocity'), block('TorqueSm')


def kinova_bags(out: Path) -> tuple[Path, Path]:
    """(training, held-out) bags: opti_traj_testing1 and opti_traj_testing2."""
    root = data_dir() / 'kinova_gen3'
    urdf = (root / 'gen3_7dof.urdf').read_text()
    names = [f'joint_{i}' for i in range(1, 8)]
    bags = []
    for label, csv in (('train', 'opti_traj_testing1'), ('heldout', 'opti_traj_testing2')):
        t, q, qd, tau = kinova_columns(root / f'{csv}.csv')
        bags.append(joint_state_bag(Path(out) / f'kinova_{label}', t, names, q, qd, tau, urdf))
    return bags[0], bags[1]


def identify_recording(name: str, out: Path, extra: Sequence[str] = ()) -> dict:
    """Convert recording ``name`` (of RECORDINGS), identify it with the defaults (held out:
    the other bag) and score it (corpus.score, masses against the URDF only)."""
    from corpus import run_identify, score

    train, heldout = (tx40_bags if name == 'tx40' else kinova_bags)(out)
    code, doc = run_identify([str(train), '--validate', str(heldout), *extra])
    if code != 0 or not doc:
        raise RuntimeError(f'identify failed on {name} (exit {code})')
    return score(doc)
