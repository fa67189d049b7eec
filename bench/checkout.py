"""Imported first by every benchmark: it measures the package of its own checkout.

The checkout's root goes first on ``sys.path`` here and on ``PYTHONPATH`` for the processes a
benchmark starts. Without it, a worktree of the code before, run with this checkout's
``.venv``, would import the package the venv's editable install points at: the code after.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ['ROOT']

ROOT = Path(__file__).resolve().parents[1]
if sys.path[:1] != [str(ROOT)]:
    sys.path.insert(0, str(ROOT))
os.environ['PYTHONPATH'] = os.pathsep.join(
    [str(ROOT)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep)
                   if p and p != str(ROOT)])
