"""The commit log of a segment: one fixed-size, checksummed record per committed episode.

An episode counts as committed once its record is in the log; the record is appended only after
the episode's field data is written (and, in a durable store, fsynced), so a record never points
at data that is not there. Record layout (little-endian)::

    magic b"IRE1" | steps u32 | episode id u64 | first transition position u64 |
    crc32 of the episode's bytes of each field, u32 each (fields in declaration order) |
    crc32 of everything before, u32

A writer appends a record with one ``write`` call, so a process killed mid-append leaves a prefix
of a record: a *short* tail is torn (never committed) and is cut off on reopen. A record of full
length whose checksum fails is damage to committed data and raises :class:`ReplayCorruptionError`.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

__all__ = ["EpisodeRecord", "ReplayCorruptionError", "encode_record", "record_size", "scan_records"]

MAGIC = b"IRE1"
_HEAD = struct.Struct("<4sIQQ")


class ReplayCorruptionError(ValueError):
    """Committed replay data fails its checksum or its size; the message names the file."""


@dataclass(frozen=True, kw_only=True)
class EpisodeRecord:
    steps: int
    episode_id: int
    first_position: int  # absolute transition number of the episode's first step
    crcs: tuple[int, ...]  # one per field, declaration order


def record_size(num_fields: int) -> int:
    return _HEAD.size + 4 * num_fields + 4


def encode_record(record: EpisodeRecord) -> bytes:
    body = _HEAD.pack(MAGIC, record.steps, record.episode_id, record.first_position) + struct.pack(
        f"<{len(record.crcs)}I", *record.crcs)
    return body + struct.pack("<I", zlib.crc32(body))


def scan_records(data: bytes, num_fields: int, path: str) -> tuple[list[EpisodeRecord], int]:
    """``(records, bytes they span)`` of a log's contents; a short tail is left out (torn or still
    being written); a full-length record that fails its checks raises, naming ``path``."""
    size = record_size(num_fields)
    records = []
    for offset in range(0, len(data) - size + 1, size):
        chunk = data[offset:offset + size]
        (crc,) = struct.unpack_from("<I", chunk, size - 4)
        magic, steps, episode_id, first = _HEAD.unpack_from(chunk)
        if magic != MAGIC or zlib.crc32(chunk[:-4]) != crc:
            raise ReplayCorruptionError(
                f"{path}: commit record {offset // size} (byte {offset}) fails its checksum; the segment is damaged: "
                f"restore it from a copy or move its folder out of the store")
        crcs = struct.unpack_from(f"<{num_fields}I", chunk, _HEAD.size)
        records.append(EpisodeRecord(steps=steps, episode_id=episode_id, first_position=first, crcs=crcs))
    return records, len(records) * size
