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
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename is None and exc.errno is not None:
            # a failed write (disk full) names no file: name the one being written
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise


def writable_directory(directory: str | os.PathLike, what: str) -> Path:
    """``directory``, created if needed, once a file could be made in it (before any long
    computation); IdentificationError saying why not otherwise (``what`` goes there)."""
    from identification_node.error_lines import os_error_line
    from identification_node.errors import IdentificationError
    path = Path(directory)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix='.probe.', dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise IdentificationError(f'cannot write {what} into {str(directory)!r}: '
                                  f'{os_error_line(exc)}') from None
    return path


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


def save_figure(fig, path: str | os.PathLike) -> Path:
    """Render the matplotlib figure ``fig`` to PNG at ``path`` atomically (100 dpi)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    with atomic_file(path, 'wb') as f:
        fig.savefig(f, format='png', dpi=100)
    return Path(path)
