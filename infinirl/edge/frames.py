"""The link's wire format: length-prefixed frames, each tagged with the name of its stream.

A frame is ``[name length: u8][payload length: u32, big endian][name: UTF-8][payload]``. Streams are
named (``"episodes"``, ``"weights"``, ...), so services share one connection without agreeing on
numbers; names starting ``link.`` belong to the link itself (hello, heartbeat).
"""

from __future__ import annotations

import struct

__all__ = ["FRAME_HEADER", "MAX_PAYLOAD_BYTES", "FrameError", "FrameReader", "encode_frame"]

FRAME_HEADER = struct.Struct("!BI")
#: the largest payload a frame may carry; larger messages are a protocol error, not a slow transfer
MAX_PAYLOAD_BYTES = 1 << 30


class FrameError(ValueError):
    """Bytes that are not a frame: the peer speaks another protocol or the stream is corrupt."""


def encode_frame(stream: str, payload: bytes | bytearray | memoryview) -> bytes:
    name = stream.encode()
    if not 0 < len(name) < 256:
        raise ValueError(f"stream name {stream!r} must be 1 to 255 bytes of UTF-8")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise ValueError(f"stream {stream!r}: payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    return b"".join((FRAME_HEADER.pack(len(name), len(payload)), name, payload))


class FrameReader:
    """Reassembles frames from bytes arriving in arbitrary pieces."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[tuple[str, bytes]]:
        """Append ``data``; return every frame now complete, in order."""
        self._buffer += data
        frames, offset = [], 0
        while len(self._buffer) - offset >= FRAME_HEADER.size:
            name_length, payload_length = FRAME_HEADER.unpack_from(self._buffer, offset)
            if name_length == 0 or payload_length > MAX_PAYLOAD_BYTES:
                raise FrameError(f"bad frame header (name length {name_length}, payload length {payload_length}): "
                                 "the peer does not speak the InfiniRL edge link protocol")
            end = offset + FRAME_HEADER.size + name_length + payload_length
            if len(self._buffer) < end:
                break
            start = offset + FRAME_HEADER.size
            try:
                name = bytes(self._buffer[start:start + name_length]).decode()
            except UnicodeDecodeError as exc:
                raise FrameError(f"frame stream name is not UTF-8 ({exc}): corrupt stream") from exc
            frames.append((name, bytes(self._buffer[start + name_length:end])))
            offset = end
        del self._buffer[:offset]
        return frames

    @property
    def buffered(self) -> int:
        return len(self._buffer)
