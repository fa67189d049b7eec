"""A snapshot of an IdentificationPipeline's health, taken at once (under the caller's lock)
so that its reader (the node's diagnostics) needs neither the lock nor the pipeline's insides.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identification_node.pipeline.estimate import EstimateReport
from identification_node.pipeline.rows import SmootherChoice
from identification_node.pipeline.time_offset import TimeOffset

__all__ = ['PipelineStatus']


@dataclass(frozen=True)
class PipelineStatus:
    """The pipeline's state at one moment.

    ``estimate``: the running estimate; counters since the last reset: joint state messages
    ``received``, samples ``used``, stream ``restarts``, ``rejected`` messages per reason;
    the robust gate (``gate_enabled``, ``gate_armed``, ``gate_suspended`` by a residual shift,
    ``residual_shifts`` seen); estimator updates rolled back (``numerical_failures``); valid
    samples the smoother never output (``smoother_edge``); bytes of decoded message layouts
    kept (``layout_cache_bytes``); per joint, equations left out near velocity reversals
    (``excluded_equations``, (n,)); the likely missing model terms (``model_term_warnings``);
    identified joints that rejected messages lacked (``missing_joints``, sorted); the torque's
    time offset against the motion (``time_offset``, None until estimated); the smoother in
    use (``smoother``, None while being chosen) and the samples held back for its choice
    (``holding``)."""
    estimate: EstimateReport
    received: int
    used: int
    restarts: int
    rejected: dict[str, int]
    gate_enabled: bool
    gate_armed: bool
    gate_suspended: bool
    residual_shifts: int
    numerical_failures: int
    smoother_edge: int
    layout_cache_bytes: int
    excluded_equations: np.ndarray
    model_term_warnings: list[str]
    missing_joints: list[str]
    time_offset: TimeOffset | None
    smoother: SmootherChoice | None
    holding: int
