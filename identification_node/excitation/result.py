"""The result of an excitation design: the optimised and framed trajectories and how they
were found."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from identification_node.config import Excitation
from identification_node.excitation.limits import LIMIT_KINDS, ExcitationLimits
from identification_node.excitation.trajectories import FourierTrajectory, FramedTrajectory

__all__ = ['DEFAULT_LIMIT_MARGIN', 'ExcitationResult']

DEFAULT_LIMIT_MARGIN = Excitation.margin   # fraction of every limit kept free


@dataclass
class ExcitationResult:
    """An optimised excitation and how it was found.

    trajectory: the optimised FourierTrajectory, the periodic part (verified inside every
    limit with its margin); framed: the FramedTrajectory a robot runs (ramps from and back to
    the start configuration at rest around ``periods`` periods of it); initial: the starting
    trajectory; criterion: 'cond' or 'dopt'; value, initial_value: the criterion of each on the
    periodic part (criterion_value with num_samples samples); ratios: limit_ratios of the
    framed trajectory against the limits without margin; iterations (SLSQP), evaluations
    (criterion or gradient), success, status and message (SLSQP's); scale: factor applied to
    the optimiser's amplitudes to satisfy the limits on the fine grid (1: none); runtime (s);
    margin: the limit margin; warnings: what the user should know (iteration limit, no
    improvement); clearance: the smallest collision distance on the final trajectory's dense
    grid (CollisionChecker.clearance), None without collision checking; initial_feasible:
    whether the initial guess met every constraint.
    """

    trajectory: FourierTrajectory
    initial: FourierTrajectory
    criterion: str
    value: float
    initial_value: float
    ratios: dict
    iterations: int
    evaluations: int
    success: bool
    message: str
    scale: float
    runtime: float
    num_samples: int
    limits: ExcitationLimits | None = None
    noise_std: list[float] | None = None
    framed: FramedTrajectory | None = None
    margin: float = DEFAULT_LIMIT_MARGIN
    status: int = 0
    warnings: list[str] = field(default_factory=list)
    clearance: dict | None = None
    collision: dict | None = None
    initial_feasible: bool = True

    @property
    def improved(self) -> bool:
        return self.value < self.initial_value

    def summary(self) -> dict:
        """Plain data for YAML: criterion, parts' durations, limit ratios (of the limits
        without margin), collision clearance, optimisation statistics and warnings."""
        names = self.trajectory.joint_names or []
        out: dict[str, Any] = {
            'criterion': {'name': self.criterion, 'value': self.value,
                          'initial': self.initial_value,
                          'initial_feasible': bool(self.initial_feasible),
                          'samples': self.num_samples,
                          **({'noise_std': self.noise_std} if self.noise_std else {})},
        }
        if self.framed is not None:
            out['durations'] = self.framed.parts()
        out['limit_margin'] = self.margin
        out['limit_ratios'] = {
            k: {'worst': float(self.ratios[k]),
                'joint': names[self.ratios['worst_joint'][k]] if names
                else int(self.ratios['worst_joint'][k]),
                'per_joint': [float(v) for v in self.ratios['per_joint'][k]]}
            for k in LIMIT_KINDS}
        if self.collision is not None:
            c = self.clearance or {}
            out['collision'] = {**self.collision, 'clearance': c.get('distance'),
                                'closest_pair': list(c['pair']) if c.get('pair') else None}
        out['optimisation'] = {'method': 'SLSQP', 'iterations': self.iterations,
                               'evaluations': self.evaluations, 'success': bool(self.success),
                               'status': self.status, 'message': self.message,
                               'scale': self.scale, 'runtime': round(self.runtime, 3)}
        out['warnings'] = list(self.warnings)
        return out
