"""What crosses the link, made small: episodes go up with compressed camera frames, weights come
down as compressed deltas against the version the edge holds when that is smaller than the full set.

**Episodes** (:func:`encode_episode` / :func:`decode_episode`). Every ``pixels.<camera>`` field
(``uint8``, ``T x H x W x 3``) is sent frame by frame as JPEG or PNG (:class:`FrameOptions`),
optionally resized to the training resolution first; every other field (state, action, reward,
...) is sent exactly (zlib of the raw bytes). PNG is lossless; JPEG is lossy (the tests bound the mean
absolute pixel error of camera-like frames at ``quality`` 90 by 3 grey levels).

**Weights** (:func:`encode_weights` / :func:`decode_weights`). The cloud keeps, per edge, the exact
weights that edge holds (:class:`HeldWeights`: version, float tensors, and a SHA-256 digest of
them). A new version goes as a *delta*, ``float16(new - held)`` per floating tensor, when that
compresses to fewer bytes than the full float32 tensors (the float32 ``full`` is sent otherwise,
always for a first push, and for deltas a float16 cannot hold). The edge adds the delta to what it
holds; both ends compute the same float32 sum, so the cloud's copy of the edge's weights stays
exact and rounding errors never accumulate over versions: each version is within
``|new - held| * 2**-11 + 2**-24 + |new| * 2**-23`` of the trainer's weights (float16 rounding of
the delta, float16's smallest step, float32's rounding of the sum). A delta names its base version
and the base's digest: against any other base it is refused (:class:`WeightBaseError`), and the
edge asks for a full push. Non-float tensors are always sent whole.
"""

from __future__ import annotations

import hashlib
import io
import json
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np

__all__ = ["FrameOptions", "HeldWeights", "WeightBaseError", "check_episode_file", "decode_episode", "decode_weights",
           "encode_episode", "encode_weights", "weights_digest", "weights_header"]

_EPISODE_MAGIC, _WEIGHTS_MAGIC = b"IEP1", b"IWT1"
_LENGTH = struct.Struct("!I")
_ZLIB_LEVEL = 1  # the link is slow, but so is an edge CPU: level 1 gets most of zlib's gain on floats


class WeightBaseError(ValueError):
    """A weight delta arrived for a base this edge does not hold."""


@dataclass(frozen=True, kw_only=True)
class FrameOptions:
    """How camera frames go up: ``format`` ``"jpeg"`` (lossy, ``quality`` 1-95) or ``"png"``
    (lossless); ``size`` (height, width) resizes first (None: as recorded)."""

    format: str = "jpeg"
    quality: int = 90
    size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if self.format not in ("jpeg", "png"):
            raise ValueError(f"frame format {self.format!r}: choose 'jpeg' or 'png'")
        if not 1 <= self.quality <= 95:
            raise ValueError(f"JPEG quality {self.quality} must be within 1..95")


def _pack(header: dict, body: bytes, magic: bytes) -> bytes:
    encoded = json.dumps(header).encode()
    return b"".join((magic, _LENGTH.pack(len(encoded)), encoded, body))


def _unpack(payload: bytes, magic: bytes, what: str) -> tuple[dict, memoryview]:
    if payload[:4] != magic:
        raise ValueError(f"not an encoded {what} (magic {bytes(payload[:4])!r}, expected {magic!r})")
    (length,) = _LENGTH.unpack_from(payload, 4)
    start = 4 + _LENGTH.size
    return json.loads(payload[start:start + length]), memoryview(payload)[start + length:]


def _encode_frame(frame: np.ndarray, options: FrameOptions) -> bytes:
    from PIL import Image

    image = Image.fromarray(frame)
    if options.size is not None and image.size != (options.size[1], options.size[0]):
        image = image.resize((options.size[1], options.size[0]), Image.BILINEAR)
    out = io.BytesIO()
    if options.format == "jpeg":
        image.save(out, format="JPEG", quality=options.quality)
    else:
        image.save(out, format="PNG", compress_level=1)
    return out.getvalue()


def _decode_frame(data: bytes) -> np.ndarray:
    from PIL import Image

    with Image.open(io.BytesIO(data)) as image:
        return np.asarray(image.convert("RGB"))


def _is_frames(name: str, array: np.ndarray) -> bool:
    return name.startswith("pixels.") and array.dtype == np.uint8 and array.ndim == 4 and array.shape[-1] == 3


def encode_episode(episode: Mapping[str, np.ndarray], *, episode_id: str,
                   frames: FrameOptions | None = None) -> bytes:
    """One episode (``field -> array``) as bytes for the link (see the module docstring)."""
    frames = frames or FrameOptions()
    fields, blobs = [], []
    for name, value in episode.items():
        array = np.ascontiguousarray(value)
        if _is_frames(name, array):
            encoded = [_encode_frame(frame, frames) for frame in array]
            size = frames.size or array.shape[1:3]
            fields.append({"name": name, "codec": frames.format, "dtype": "uint8",
                           "shape": [len(array), *size, 3], "sizes": [len(e) for e in encoded]})
            blobs.extend(encoded)
        else:
            packed = zlib.compress(array.tobytes(), _ZLIB_LEVEL)
            fields.append({"name": name, "codec": "zlib", "dtype": array.dtype.str, "shape": list(array.shape),
                           "sizes": [len(packed)]})
            blobs.append(packed)
    return _pack({"id": episode_id, "fields": fields}, b"".join(blobs), _EPISODE_MAGIC)


def decode_episode(payload: bytes) -> tuple[str, dict[str, np.ndarray]]:
    """``(episode_id, episode)`` from :func:`encode_episode`'s bytes."""
    header, body = _unpack(payload, _EPISODE_MAGIC, "episode")
    episode, offset = {}, 0
    for field in header["fields"]:
        parts = []
        for size in field["sizes"]:
            parts.append(bytes(body[offset:offset + size]))
            offset += size
        if field["codec"] == "zlib":
            array = np.frombuffer(zlib.decompress(parts[0]), np.dtype(field["dtype"])).reshape(field["shape"])
        else:
            array = np.stack([_decode_frame(part) for part in parts]) if parts else np.zeros(field["shape"], np.uint8)
        if list(array.shape) != field["shape"]:
            raise ValueError(f"episode {header['id']}: field {field['name']} decoded to {array.shape}, "
                             f"header says {field['shape']}")
        episode[field["name"]] = array.copy()
    return header["id"], episode


def check_episode_file(handle: BinaryIO, size: int) -> str:
    """The id of the encoded episode in ``handle`` (``size`` bytes), after checking that the bytes
    are its header and exactly the body that header describes; ``ValueError`` naming what is wrong.
    Reads the header only, so a folder of large episodes is checked quickly (a torn or truncated
    file differs in its magic or its length)."""
    prefix = handle.read(len(_EPISODE_MAGIC) + _LENGTH.size)
    if len(prefix) < len(_EPISODE_MAGIC) + _LENGTH.size or prefix[:4] != _EPISODE_MAGIC:
        raise ValueError(f"not an encoded episode ({size} bytes, starting {prefix[:8]!r})")
    (length,) = _LENGTH.unpack_from(prefix, 4)
    start = len(prefix) + length
    if start > size:
        raise ValueError(f"truncated: {size} bytes, but its header alone is {start}")
    try:
        header = json.loads(handle.read(length))
        body = sum(int(part) for field in header["fields"] for part in field["sizes"])
        episode_id = header["id"]
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"its header is malformed ({exc!r})") from None
    if start + body != size or not isinstance(episode_id, str):
        raise ValueError(f"{size} bytes, but its header describes {start + body}"
                         if start + body != size else f"episode id {episode_id!r} is not a string")
    return episode_id


# ---------------------------------------------------------------------------------------- weights
def weights_digest(tensors: Mapping[str, np.ndarray]) -> str:
    """SHA-256 over the names, dtypes, shapes and bytes of ``tensors`` (in name order)."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        array = np.ascontiguousarray(tensors[name])
        digest.update(f"{name}|{array.dtype.str}|{array.shape}|".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


@dataclass(frozen=True, kw_only=True)
class HeldWeights:
    """The weights one edge holds: ``version``, ``tensors`` and their :func:`weights_digest`."""

    version: int
    tensors: dict[str, np.ndarray]
    digest: str

    @classmethod
    def of(cls, version: int, tensors: Mapping[str, np.ndarray]) -> HeldWeights:
        tensors = {name: np.ascontiguousarray(value) for name, value in tensors.items()}
        return cls(version=version, tensors=tensors, digest=weights_digest(tensors))


def _as_float32(tensors: Mapping[str, object]) -> dict[str, np.ndarray]:
    out = {}
    for name, value in tensors.items():
        if hasattr(value, "detach"):  # a torch tensor
            value = value.detach().cpu().numpy()
        array = np.asarray(value)
        out[name] = array.astype(np.float32) if np.issubdtype(array.dtype, np.floating) else array
    return out


def _delta(new: Mapping[str, np.ndarray], base: HeldWeights) -> dict[str, np.ndarray] | None:
    """float16 differences of the float tensors, or None when the layouts differ or one does not fit."""
    if set(new) != set(base.tensors):
        return None
    deltas = {}
    for name, array in new.items():
        held = base.tensors[name]
        if held.shape != array.shape or held.dtype != array.dtype:
            return None
        if array.dtype == np.float32:
            difference = array.astype(np.float64) - held.astype(np.float64)
            if not np.all(np.abs(difference) <= np.finfo(np.float16).max):
                return None
            deltas[name] = difference.astype(np.float16)
    return deltas


def encode_weights(tensors: Mapping[str, object], version: int, base: HeldWeights | None = None,
                   *, allow_delta: bool = True) -> tuple[bytes, HeldWeights]:
    """Bytes for the link, and the :class:`HeldWeights` the edge will hold once it decodes them
    (keep it as the edge's next base). A delta against ``base`` when that is smaller."""
    new = _as_float32(tensors)
    names = sorted(new)
    full_body = zlib.compress(b"".join(new[name].tobytes() for name in names), _ZLIB_LEVEL)
    full_fields = [{"name": n, "dtype": new[n].dtype.str, "shape": list(new[n].shape), "codec": "raw"} for n in names]
    choice = ("full", full_body, full_fields, HeldWeights.of(version, new))
    deltas = _delta(new, base) if (allow_delta and base is not None) else None
    if deltas is not None:
        parts, fields, held = [], [], {}
        for name in names:
            if name in deltas:
                parts.append(deltas[name].tobytes())
                held[name] = base.tensors[name] + deltas[name].astype(np.float32)
                fields.append({"name": name, "dtype": new[name].dtype.str, "shape": list(new[name].shape),
                               "codec": "fp16delta"})
            else:
                parts.append(new[name].tobytes())
                held[name] = new[name]
                fields.append(full_fields[names.index(name)])
        delta_body = zlib.compress(b"".join(parts), _ZLIB_LEVEL)
        if len(delta_body) < len(full_body):
            choice = ("delta", delta_body, fields, HeldWeights.of(version, held))
    kind, body, fields, result = choice
    header = {"version": version, "kind": kind, "tensors": fields, "digest": result.digest,
              "base_version": base.version if kind == "delta" else None,
              "base_digest": base.digest if kind == "delta" else None}
    return _pack(header, body, _WEIGHTS_MAGIC), result


def weights_header(payload: bytes) -> dict:
    """The header of encoded weights (version, kind, base) without decoding the tensors."""
    return _unpack(payload, _WEIGHTS_MAGIC, "weights message")[0]


def decode_weights(payload: bytes, held: HeldWeights | None) -> HeldWeights:
    """The weights after applying ``payload`` to ``held``; a delta for another base raises
    :class:`WeightBaseError`; a result whose digest differs from the sender's raises ``ValueError``."""
    header, body = _unpack(payload, _WEIGHTS_MAGIC, "weights message")
    if header["kind"] == "delta":
        if held is None or held.version != header["base_version"] or held.digest != header["base_digest"]:
            have = "no weights" if held is None else f"version {held.version} ({held.digest[:12]})"
            raise WeightBaseError(f"weight delta for version {header['version']} is against base version "
                                  f"{header['base_version']} ({header['base_digest'][:12]}), but this edge holds "
                                  f"{have}; a full push is needed")
    raw, offset, tensors = zlib.decompress(body), 0, {}
    for field in header["tensors"]:
        dtype = np.dtype("float16") if field["codec"] == "fp16delta" else np.dtype(field["dtype"])
        count = int(np.prod(field["shape"], dtype=np.int64))
        array = np.frombuffer(raw, dtype, count, offset).reshape(field["shape"])
        offset += count * dtype.itemsize
        if field["codec"] == "fp16delta":
            array = held.tensors[field["name"]] + array.astype(np.float32)
        tensors[field["name"]] = array.copy()
    result = HeldWeights.of(header["version"], tensors)
    if result.digest != header["digest"]:
        raise ValueError(f"weights version {header['version']} decoded to digest {result.digest[:12]}, the sender "
                         f"computed {header['digest'][:12]}: corrupt transfer or a different numpy arithmetic")
    return result
