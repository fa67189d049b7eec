"""Atomic file output: write to a temporary sibling, then rename into place."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import yaml


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` so readers see the old file or the whole new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        with os.fdopen(fd, 'w') as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def atomic_write_yaml(path: str | os.PathLike, data: object) -> Path:
    """YAML dump of plain Python data (lists, dicts, floats), written atomically."""
    return atomic_write_text(path, yaml.safe_dump(data, sort_keys=False))
