"""Estimators on the information form: least squares, recursive least squares, residual statistics,
robust gating, the physically consistent solve."""
