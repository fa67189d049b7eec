"""Estimators on the information form: batch least squares (``batch``), recursive least
squares (``rls``), residual statistics (``residuals``), their shared helpers (``lsq``), robust
gating, the physically consistent solve."""
