"""Offline robustness (issue 31): every OS and parse error on an input or output path is one
line naming the file or option (cli.main + error_lines.py), writers replace only bags, YAML is
read with limits (safe_yaml.py)."""
import errno
import os
import time
from pathlib import Path

import pytest

from identification_node.bags.reader import open_bag
from identification_node.bags.writer import BagWriter, not_a_bag
from identification_node.cli import main
from identification_node.errors import IdentificationError
from identification_node.error_lines import error_line
from identification_node.safe_yaml import load_yaml, read_yaml

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / 'bags' / 'mit_paper_moves'
CONFIG = ROOT / 'config' / 'identification.yaml'


def one_line(capsys, argv, *words):
    """Run the CLI in-process: exit 2 and one stderr line holding ``words``."""
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and 'Traceback' not in err, err
    assert err.startswith('error: ') and 'failed:' not in err, err
    for word in words:
        assert str(word).lower() in err.lower(), err
    return err


def bomb(levels: int) -> str:
    """A YAML mapping whose last key stands for 2**levels leaves through nested aliases."""
    lines = ['b0: &b0 {x: 1}']
    lines += [f'b{i}: &b{i} {{l: *b{i - 1}, r: *b{i - 1}}}' for i in range(1, levels + 1)]
    return '\n'.join(lines) + '\n'


# -- OS errors on output paths ---------------------------------------------------------------
def test_a_full_disk_is_one_line_naming_the_file(tmp_path, capsys, monkeypatch):
    """The kernel's own ENOSPC: the atomic writer's file is /dev/full."""
    real = os.fdopen

    def full(fd, mode='r', *a, **k):
        os.close(fd)
        return real(os.open('/dev/full', os.O_WRONLY), mode, *a, **k)
    monkeypatch.setattr(os, 'fdopen', full)
    out = tmp_path / 'sim'
    one_line(capsys, ['simulate', '--robot', 'mit_dd_arm', '--duration', '0.05', '--out', out],
             'no space left on the device', out / 'true_parameters.yaml')
    assert not any(p.name.endswith('.tmp') for p in out.iterdir())   # nothing half-written


def test_a_full_disk_while_writing_a_bag_names_the_bag(tmp_path, capsys, monkeypatch):
    """The kernel's ENOSPC from /dev/full under the bag's storage file."""
    import builtins
    real = builtins.open

    def full_storage(file, mode='r', *a, **k):
        if set('wx') & set(str(mode)) and str(file).endswith('.mcap'):
            return real('/dev/full', str(mode).replace('x', 'w'), *a, **k)
        return real(file, mode, *a, **k)
    monkeypatch.setattr(builtins, 'open', full_storage)
    monkeypatch.setattr(Path, 'open', lambda self, mode='r', *a, **k: full_storage(
        self, mode, *a, **k))
    out = tmp_path / 'sim'
    one_line(capsys, ['simulate', '--robot', 'mit_dd_arm', '--duration', '0.5', '--out', out],
             'bag', str(out), 'no space left on the device')
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name != 'sim']


@pytest.mark.parametrize('code, words', [
    (errno.EROFS, 'the file system is read-only'),
    (errno.ENOSPC, 'no space left'),
    (errno.EACCES, 'permission denied')])
def test_os_errors_creating_an_output_directory(tmp_path, capsys, monkeypatch, code, words):
    def refuse(self, *a, **k):
        raise OSError(code, os.strerror(code), str(self))
    monkeypatch.setattr(Path, 'mkdir', refuse)
    out = tmp_path / 'saved'
    one_line(capsys, ['identify', BAG, '--config', CONFIG, '--save', out], '--save', out, words)


def test_files_in_the_way_of_output_directories(tmp_path, capsys):
    blocker = tmp_path / 'file'
    blocker.write_text('mine')
    one_line(capsys, ['identify', BAG, '--save', blocker], blocker,
             'exists and is not a directory')
    one_line(capsys, ['identify', BAG, '--save', '/dev/zero'], '/dev/zero',
             'exists and is not a directory')
    one_line(capsys, ['identify', BAG, '--save', '/dev/zero/out'], '/dev/zero/out',
             'a part of the path is not a directory')
    long = tmp_path / ('x' * 300)
    one_line(capsys, ['identify', BAG, '--save', long], 'file name too long')
    assert blocker.read_text() == 'mine'


def test_error_lines_of_the_remaining_kinds():
    assert error_line(FileExistsError(errno.EEXIST, 'File exists', '/nonexistent/x')) == \
        "'/nonexistent/x': exists already"
    assert 'binary' in error_line(_decode_error())
    assert 'out of range' in error_line(OverflowError('cannot convert float infinity'))
    assert 'out of memory' in error_line(MemoryError())
    assert error_line(ValueError('a bug')) is None


def _decode_error():
    try:
        b'\x96'.decode('utf-8')
    except UnicodeDecodeError as exc:
        return exc


# -- options out of range -----------------------------------------------------------
def test_a_window_past_the_bags_end(capsys):
    one_line(capsys, ['identify', BAG, '--config', CONFIG, '--start', '1e300'],
             '--start', 'after the end of the bag')
    with open_bag(BAG) as bag:
        span = bag.duration
    from identification_node.bags.windows import TimeWindow
    with open_bag(BAG) as bag:   # an end far past the bag: the bag's end
        assert TimeWindow(0.5, 1e300).bounds_ns(str(BAG), bag.start_ns, bag.end_ns) == (
            bag.start_ns + 500_000_000, bag.end_ns + 1)
    assert span > 1


def test_structure_samples_is_validated_not_allocated(capsys):
    one_line(capsys, ['structure', '--robot', 'mit_dd_arm', '--samples', '100000000'],
             '--samples 100000000', 'at most')


# -- bad --config files ----------------------------------------------------------------------
@pytest.mark.parametrize('content, words', [
    (os.urandom(64) + b'\x96', 'is not UTF-8 text'),
    (b'- a\n- list\n', 'does not hold a mapping'),
    (b'node:\n  ros__parameters: [1, 2]\n', 'ros__parameters is not a mapping'),
    (b'a: [1, 2\nb: 3\n', 'not valid YAML'),
    (b'a: !!float "abc"\n', 'not valid YAML: could not convert'),
    (bomb(40).encode(), 'YAML bomb')])
@pytest.mark.parametrize('verb', ['identify', 'simulate', 'node'])
def test_bad_config_files_are_one_line(tmp_path, capsys, content, words, verb):
    path = tmp_path / 'config.yaml'
    path.write_bytes(content)
    if verb == 'node':   # the node's check of its --params-file, before rclpy sees it
        from identification_node.ros.spin import check_parameter_files
        with pytest.raises(IdentificationError, match=words) as info:
            check_parameter_files(['--ros-args', '--params-file', str(path)])
        assert str(path) in str(info.value) and '\n' not in str(info.value)
        return
    argv = ([verb, BAG] if verb == 'identify' else [verb, '--out', tmp_path / 'o'])
    one_line(capsys, argv + ['--config', path], path, words)


def test_yaml_bomb_refused_at_once_and_plain_aliases_kept():
    start = time.process_time()
    with pytest.raises(IdentificationError, match='YAML bomb'):
        load_yaml(bomb(60), 'bomb')
    assert time.process_time() - start < 1.0   # linear in the text, not in its expansion
    assert load_yaml('a: &x {k: 1}\nb: *x\n') == {'a': {'k': 1}, 'b': {'k': 1}}
    assert load_yaml(bomb(10), 'ok')['b10']['l']['r']['l']['l']['r']['r']['l']['l']['r']['l'] \
        == {'x': 1}
    assert load_yaml('') is None


def test_read_yaml_limits_size(tmp_path, monkeypatch):
    import identification_node.safe_yaml as safe_yaml
    monkeypatch.setattr(safe_yaml, 'MAX_BYTES', 100)
    path = tmp_path / 'big.yaml'
    path.write_text('a: ' + 'x' * 200 + '\n')
    with pytest.raises(IdentificationError, match='more than'):
        read_yaml(path)


# -- writers replace only bags ---------------------------------------------------------------
def _user_folder(path: Path) -> Path:
    (path / 'sub').mkdir(parents=True)
    (path / 'thesis.txt').write_text('years of work')
    (path / 'sub' / 'data.csv').write_text('1,2\n')
    return path


def _tree(path: Path) -> dict:
    return {str(p.relative_to(path)): p.read_bytes() for p in path.rglob('*') if p.is_file()}


def test_simulate_overwrite_replaces_only_a_bag(tmp_path, capsys):
    argv = ['simulate', '--robot', 'mit_dd_arm', '--duration', '0.05', '--overwrite', '--out']
    folder = _user_folder(tmp_path / 'folder')
    before = _tree(folder)
    one_line(capsys, argv + [folder], '--out', 'is not a bag', 'thesis.txt')
    assert _tree(folder) == before
    regular = tmp_path / 'file.txt'
    regular.write_text('mine')
    one_line(capsys, argv + [regular], 'is not a bag', 'not a directory')
    assert regular.read_text() == 'mine'
    bag = tmp_path / 'bag'
    assert main(argv + [str(bag)]) == 0 and main(argv + [str(bag)]) == 0   # a bag: replaced
    assert not_a_bag(bag) is None and (bag / 'true_parameters.yaml').is_file()
    (bag / 'notes.txt').write_text('added by hand')
    one_line(capsys, argv + [bag], 'notes.txt')


def test_record_overwrite_refuses_before_starting_ros(tmp_path, capsys):
    folder = _user_folder(tmp_path / 'folder')
    before = _tree(folder)
    one_line(capsys, ['record', folder, '--topics', '/x', '--overwrite'], 'OUT', folder,
             'is not a bag')
    assert _tree(folder) == before


def test_the_bag_writer_itself_refuses_to_replace_other_things(tmp_path):
    folder = _user_folder(tmp_path / 'folder')
    with pytest.raises(IdentificationError, match='thesis.txt'):
        BagWriter(folder, overwrite=True)
    empty = tmp_path / 'empty'
    empty.mkdir()
    assert 'without metadata.yaml' in not_a_bag(empty)
    link = tmp_path / 'link'
    link.symlink_to(folder)
    assert not_a_bag(link) == 'a symbolic link'
    assert not_a_bag(tmp_path / 'absent') is None and not_a_bag(BAG) is None


def _unshare_available() -> bool:
    import shutil
    import subprocess
    return shutil.which('unshare') is not None and subprocess.run(
        ['unshare', '-rm', 'true'], capture_output=True).returncode == 0


@pytest.mark.slow
@pytest.mark.skipif(not _unshare_available(), reason='no user namespaces (unshare -rm)')
@pytest.mark.parametrize('options, words', [
    ('ro', 'the file system is read-only'), ('size=16k', 'no space left on the device')])
def test_real_read_only_and_full_file_systems(tmp_path, options, words):
    """The kernel's own EROFS and ENOSPC: a tmpfs mounted read-only or 16 KiB small in a
    private mount namespace (no root needed)."""
    import subprocess
    import sys
    mount = tmp_path / 'mnt'
    mount.mkdir()
    script = (f'mount -t tmpfs -o {options} tmpfs {mount} && exec {sys.executable} -m '
              f'identification_node simulate --robot mit_dd_arm --duration 2 --out {mount}/bag')
    out = subprocess.run(['unshare', '-rm', 'sh', '-c', script], capture_output=True,
                         text=True, timeout=120)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and 'Traceback' not in out.stderr, out.stderr
    assert words in lines[0].lower() and str(mount) in lines[0], lines[0]
