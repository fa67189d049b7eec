"""Atomic file output: write to a temporary sibling, then rename into place."""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import IO, Iterator

import yaml


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike, mode: str = 'w') -> Iterator[IO]:
    """A temporary sibling of ``path`` open for writing (``mode`` 'w' or 'wb'); it replaces
    ``path`` when the block ends without error, so readers see the old file or the whole new
    one, and it is removed otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~umask())   # mkstemp makes 0600; a plain open() would not
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def umask() -> int:
    """The process's file mode creation mask (read without changing it where Linux allows)."""
    try:
        with open('/proc/self/status') as f:
            for line in f:
                if line.startswith('Umask:'):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)   # elsewhere: set and restore (not atomic across threads)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically."""
    with atomic_file(path) as f:
        f.write(text)
    return Path(path)


def atomic_write_yaml(path: str | os.PathLike, data: object) -> Path:
    """YAML dump of plain Python data (lists, dicts, floats), written atomically."""
    return atomic_write_text(path, yaml.safe_dump(data, sort_keys=False))
