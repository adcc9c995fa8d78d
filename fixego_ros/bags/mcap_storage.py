"""rosbags' rosbag2 :class:`~rosbags.rosbag2.Writer` with MCAP files that carry real CRCs (both of our writers use it).

rosbags' MCAP storage writes every CRC as 0 ("not computed" in the MCAP spec), so a flipped bit in a bag goes
unnoticed: zstd stores incompressible data (our camera images) as raw blocks, which decompress without error
whatever they hold. :class:`CrcMcapWriter` is that storage with the three CRCs the format has filled in:

* each Chunk's ``uncompressed_crc`` (CRC-32 of the chunk's records before compression), written when the
  chunk is closed, so a recording killed later still has checked chunks;
* DataEnd's ``data_section_crc`` (every byte from the magic up to the DataEnd record) and
* the Footer's ``summary_crc`` (the summary section through the footer's ``summary_offset_start``),
  both patched in place once rosbags has closed the file.

Only fixed-size CRC fields change, at offsets the MCAP specification fixes, so everything else (records,
``metadata.yaml``, topics, QoS, type hashes) is rosbags' output unchanged, and the same input gives the same
bytes. :func:`fixego_ros.bags.reader.Bag` validates these CRCs whenever they are non-zero.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import McapWriter

MAGIC = b'\x89MCAP0\r\n'
_CHUNK_CRC_AT = 1 + 8 + 8 + 8 + 8          # opcode, record length, start time, end time, uncompressed size
_FOOTER_SIZE = 1 + 8 + 8 + 8 + 4           # opcode, record length, summary start, summary offset start, CRC
_DATA_END_SIZE = 1 + 8 + 4                 # opcode, record length, data section CRC
OP_FOOTER, OP_DATA_END = 0x02, 0x0F


class CrcMcapWriter(McapWriter):
    """rosbags' MCAP storage writer, with chunk, data-section and summary CRCs (module docstring)."""

    def close_chunk(self) -> None:
        """Write the pending chunk as rosbags does, then its CRC into the record just written."""
        crc = zlib.crc32(self.chunk.bio.getbuffer())
        start = self.bio.tell()
        super().close_chunk()
        end = self.bio.tell()
        self.bio.seek(start + _CHUNK_CRC_AT)
        self.bio.write(struct.pack('<I', crc))
        self.bio.seek(end)

    def close(self, version: int, metadata: str) -> None:
        super().close(version, metadata)
        seal(self.path)


def seal(path: str | Path) -> None:
    """Fill in the data-section and summary CRCs of a complete MCAP file whose CRCs are 0 (rosbags' output).

    Raises ``ValueError`` when the file does not end with a footer preceded by DataEnd where the footer says.
    """
    path = Path(path)
    with path.open('r+b') as fh:
        size = fh.seek(0, 2)
        footer_at = size - len(MAGIC) - _FOOTER_SIZE
        if footer_at < len(MAGIC):
            raise ValueError(f'{path}: too short for an MCAP file with a footer')
        fh.seek(footer_at)
        tail = fh.read(_FOOTER_SIZE + len(MAGIC))
        op, length, summary_start, _summary_offset_start, _ = struct.unpack('<BQQQI', tail[:_FOOTER_SIZE])
        if op != OP_FOOTER or length != _FOOTER_SIZE - 9 or tail[_FOOTER_SIZE:] != MAGIC:
            raise ValueError(f'{path}: no MCAP footer at the end of the file')
        data_end_at = (summary_start or footer_at) - _DATA_END_SIZE
        fh.seek(data_end_at)
        op, length = struct.unpack('<BQ', fh.read(9))
        if op != OP_DATA_END or length != 4:
            raise ValueError(f'{path}: no DataEnd record before the summary section')
        data_crc = _crc_of(fh, 0, data_end_at)
        fh.seek(data_end_at + 9)
        fh.write(struct.pack('<I', data_crc))
        summary_crc = _crc_of(fh, summary_start or footer_at, footer_at + _FOOTER_SIZE - 4)
        fh.seek(footer_at + _FOOTER_SIZE - 4)
        fh.write(struct.pack('<I', summary_crc))


def _crc_of(fh: Any, start: int, end: int, block: int = 1 << 20) -> int:
    """CRC-32 of bytes ``[start, end)`` of ``fh`` (read in blocks: bags are large)."""
    fh.seek(start)
    crc, left = 0, end - start
    while left > 0:
        data = fh.read(min(block, left))
        if not data:
            raise ValueError('file shorter than expected')
        crc = zlib.crc32(data, crc)
        left -= len(data)
    return crc


class CrcWriter(Writer):
    """rosbags' rosbag2 writer whose MCAP storage writes CRCs (:class:`CrcMcapWriter`)."""

    STORAGE_PLUGINS: ClassVar[Mapping[StoragePlugin, Any]] = {**Writer.STORAGE_PLUGINS,
                                                               StoragePlugin.MCAP: CrcMcapWriter}


def bag_writer(path: str | Path, compression: bool = True) -> Writer:
    """A rosbag2 (version 9) writer to ``path`` with MCAP storage, CRCs and, by default, zstd chunk compression
    (like rosbag2's mcap plugin with a zstd chunk profile: no rosbag2-level compression in metadata.yaml)."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode

    writer = CrcWriter(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compression:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    return writer
