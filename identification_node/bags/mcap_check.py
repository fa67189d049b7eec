"""Chunk checksums of mcap files: verified on read, written on write (with the `mcap` library).

An mcap chunk record holds the CRC-32 of its uncompressed records (0: not computed). Bags
from ``ros2 bag record`` carry them; the rosbags writer leaves them 0, so a flipped bit in a
message would change a result silently. :func:`add_chunk_crcs` fills them in after writing
(the field only: nothing else of the file changes) and :func:`verify_chunks` checks every
chunk before a bag is read, naming the corrupt chunk.
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

from identification_node.errors import IdentificationError

# A chunk record: opcode (1), record length (8), then message start/end time, uncompressed
# size (8 each) and the uncompressed CRC (4): its byte offset from the record's start.
_CRC_OFFSET = 1 + 8 + 24


def mcap_chunks(f) -> list:
    """The chunk indexes of an open mcap file (its summary), in file order."""
    from mcap.reader import make_reader
    summary = make_reader(f).get_summary()
    if summary is None:
        return []
    return sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)


def _read_chunk(f, index):
    from mcap.records import Chunk
    from mcap.data_stream import ReadDataStream
    f.seek(index.chunk_start_offset + 9)
    return Chunk.read(ReadDataStream(f))


def _records(chunk) -> bytes:
    """The chunk's uncompressed records (what its CRC covers)."""
    from mcap.stream_reader import get_chunk_data_stream
    stream, length = get_chunk_data_stream(chunk, validate_crc=False)
    return stream.read(length)


def verify_chunks(path: str | Path) -> int:
    """Check the CRC of every chunk of the mcap file ``path``; IdentificationError naming the
    chunk (number, byte offset, log time span) when one does not match or cannot be read.
    Returns how many chunks carry no CRC (those cannot be checked)."""
    path = Path(path)
    unchecked = 0
    with open(path, 'rb') as f:
        try:
            indexes = mcap_chunks(f)
        except Exception as exc:   # noqa: BLE001 - a corrupt summary: the reader names it
            raise IdentificationError(f'mcap file {path}: cannot read its chunk index '
                                      f'({type(exc).__name__}: {exc})') from None
        for k, index in enumerate(indexes):
            where = (f'mcap file {path}: chunk {k} (at byte {index.chunk_start_offset}, log '
                     f'times {index.message_start_time}..{index.message_end_time} ns)')
            try:
                chunk = _read_chunk(f, index)
                records = _records(chunk)
            except Exception as exc:   # noqa: BLE001 - undecodable: corrupt
                raise IdentificationError(f'{where} is corrupt: {type(exc).__name__}: '
                                          f'{exc}') from None
            if chunk.uncompressed_crc == 0:
                unchecked += 1
            elif zlib.crc32(records) != chunk.uncompressed_crc:
                raise IdentificationError(f'{where} is corrupt: its CRC does not match its '
                                          'data (a flipped bit, a bad disk or copy)')
    return unchecked


def add_chunk_crcs(path: str | Path) -> int:
    """Fill in the CRC of every chunk of the mcap file ``path`` that has none; returns how
    many were filled in."""
    filled = 0
    with open(path, 'r+b') as f:
        for index in mcap_chunks(f):
            chunk = _read_chunk(f, index)
            if chunk.uncompressed_crc:
                continue
            f.seek(index.chunk_start_offset + _CRC_OFFSET)
            f.write(struct.pack('<I', zlib.crc32(_records(chunk))))
            filled += 1
    return filled
