"""An excitation's outputs: sample times, a JointTrajectory message and the plot."""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from identification_node.errors import IdentificationError
from identification_node.excitation.limits import ExcitationLimits
from identification_node.excitation.result import DEFAULT_LIMIT_MARGIN
from identification_node.excitation.trajectories import FramedTrajectory
from identification_node.excitation.trajectory_base import Trajectory

__all__ = ['plot_excitation', 'sample_times', 'trajectory_to_joint_trajectory']


def sample_times(traj: Trajectory, rate: float, periods: int = 1) -> np.ndarray:
    """Times 0, 1/rate, ... up to and including ``periods`` passes of ``traj`` (s)."""
    if not (math.isfinite(rate) and rate > 0):
        raise IdentificationError(f'sample rate must be finite and > 0, got {rate}')
    if isinstance(periods, bool) or not isinstance(periods, (int, np.integer)) or periods < 1:
        raise IdentificationError(f'periods must be an integer >= 1, got {periods!r}')
    end = periods * traj.horizon()
    count = int(math.floor(end * rate + 1e-9))
    t = np.arange(count + 1) / rate
    return t if math.isclose(t[-1], end, abs_tol=1e-9) else np.append(t, end)


def trajectory_to_joint_trajectory(traj: Trajectory, rate: float = 100.0, periods: int = 1,
                                   joint_names: Sequence[str] | None = None,
                                   stamp: float = 0.0) -> Any:
    """A trajectory_msgs/JointTrajectory (rosbags message) of ``traj`` sampled at ``rate``
    (Hz) over ``periods`` passes including the end point: positions, velocities,
    accelerations and time_from_start per point. The motion starts at q(0) with velocity
    qd(0) (at rest for a FramedTrajectory): bring the robot there first."""
    from identification_node.bags.writer import make_joint_trajectory
    names = list(joint_names or traj.joint_names or [])
    if len(names) != traj.dof:
        raise IdentificationError(f'need {traj.dof} joint names, got {names}')
    t = sample_times(traj, rate, periods)
    q, qd, qdd = traj.sample(t)
    return make_joint_trajectory(stamp, names, t, q, qd, qdd)


def plot_excitation(framed: FramedTrajectory, limits: ExcitationLimits, path: str | os.PathLike,
                    margin: float = DEFAULT_LIMIT_MARGIN, rate: float = 100.0,
                    title: str = '') -> Path:
    """PNG of q, qd, qdd (columns) per joint (rows) against time, with the limits (dashed)
    and the limits with their margin (dotted) drawn and the ramps shaded; written
    atomically."""
    from matplotlib.figure import Figure

    from identification_node.fileio import save_figure

    t = sample_times(framed, rate)
    motion = framed.sample(t)
    work = limits.with_margin(margin)
    names = framed.joint_names or [f'q{i + 1}' for i in range(framed.dof)]
    n = framed.dof
    fig = Figure(figsize=(13, 1.2 + 1.9 * n))
    axes = fig.subplots(n, 3, sharex=True, squeeze=False)
    t0, t1 = framed.periodic_window
    bounds = [(limits.position_limits, work.position_limits)] + [
        (np.stack([-v, v], axis=1), np.stack([-w, w], axis=1))
        for v, w in ((limits.velocity_limits, work.velocity_limits),
                     (limits.acceleration_limits, work.acceleration_limits))]
    units = ('rad', 'rad/s', 'rad/s^2')
    for col, (label, x, (raw, kept)) in enumerate(zip(('position', 'velocity', 'acceleration'),
                                                      motion, bounds)):
        for j in range(n):
            ax = axes[j, col]
            ax.axvspan(0.0, t0, color='0.92')
            ax.axvspan(t1, framed.duration, color='0.92')
            ax.plot(t, x[:, j], color='tab:blue', lw=0.9)
            for value in raw[j]:
                if np.isfinite(value):
                    ax.axhline(value, color='tab:red', ls='--', lw=0.8)
            for value in kept[j]:
                if np.isfinite(value):
                    ax.axhline(value, color='tab:orange', ls=':', lw=0.8)
            ax.grid(alpha=0.3)
            ax.set_ylabel(f'{names[j]} ({units[col]})', fontsize='small')
        axes[0, col].set_title(label)
        axes[-1, col].set_xlabel('time (s)')
    fig.suptitle(title or f'excitation: ramp in {t0:.1f} s (shaded), periodic '
                 f'{t1 - t0:.1f} s, ramp out {framed.duration - t1:.1f} s; limits dashed, '
                 f'with {100 * margin:g} % margin dotted', fontsize='medium')
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 0.98))
    return save_figure(fig, Path(path))
