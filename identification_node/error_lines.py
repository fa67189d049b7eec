"""One readable line for the failures a user can meet on any input or output path: operating
system errors (disk full, read-only, name too long, a file where a directory is needed),
undecodable or malformed input files, numbers out of range and memory exhaustion.

The CLI (cli.main) and the node's start-up (ros.spin.run_node) print these instead of the
exception's type and text; other exceptions stay what they are (bugs, shown in full when
IDENTIFICATION_DEBUG is set).
"""
from __future__ import annotations

import errno
import os

# errno -> what it means for the file named (the C library's strerror is kept otherwise)
_OS_TEXT = {
    errno.ENOSPC: 'no space left on the device (free some space or write elsewhere)',
    errno.EDQUOT: 'disk quota exceeded (free some space or write elsewhere)',
    errno.EROFS: 'the file system is read-only (write elsewhere)',
    errno.ENAMETOOLONG: 'file name too long (at most 255 bytes per name)',
    errno.ENOTDIR: 'a part of the path is not a directory',
    errno.EISDIR: 'is a directory, not a file',
    errno.EACCES: 'permission denied',
    errno.EPERM: 'operation not permitted',
    errno.ENOENT: 'no such file or directory',
    errno.ELOOP: 'too many levels of symbolic links',
    errno.EMFILE: 'too many open files',
    errno.EIO: 'input/output error (a failing disk or device?)',
}


def os_error_text(exc: OSError) -> str:
    """What is wrong, for an OSError (without the path)."""
    path = exc.filename
    if exc.errno == errno.EEXIST and path is not None:
        return ('exists and is not a directory' if os.path.lexists(path)
                and not os.path.isdir(path) else 'exists already')
    known = None if exc.errno is None else _OS_TEXT.get(exc.errno)
    return known or exc.strerror or str(exc) or type(exc).__name__


def os_error_line(exc: OSError) -> str:
    """``path: what is wrong`` for an OSError (the path, when it names one)."""
    path = exc.filename
    text = os_error_text(exc)
    if path is None:
        return text[0].upper() + text[1:]
    where = f'{os.fsdecode(path)!r}'
    if exc.filename2 is not None:
        where += f' -> {os.fsdecode(exc.filename2)!r}'
    return f'{where}: {text}'


def error_line(exc: BaseException) -> str | None:
    """One line saying what is wrong for the failures of the environment or of input data
    (see the module doc), None for any other exception."""
    if isinstance(exc, OSError):
        return os_error_line(exc)
    if isinstance(exc, UnicodeDecodeError):
        return (f'an input file is not {exc.encoding} text (byte 0x{exc.object[exc.start]:02x}'
                f' at {exc.start}): is it a binary file?')
    if isinstance(exc, MemoryError):
        return ('out of memory' + (f' ({exc})' if str(exc) else '')
                + ': use less data (a time window, fewer samples)')
    if isinstance(exc, OverflowError):
        return f'a number is out of range ({exc}): check the numeric options'
    if isinstance(exc, RecursionError):
        return 'an input is nested too deeply to be read'
    try:
        import yaml
    except ImportError:   # pragma: no cover - yaml is a dependency
        return None
    if isinstance(exc, yaml.YAMLError):
        from identification_node.safe_yaml import yaml_problem
        return f'invalid YAML: {yaml_problem(exc)}'
    return None
