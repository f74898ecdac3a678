"""The services' stream names on the link and their small JSON messages.

``episodes`` (edge -> cloud): one :func:`~infinirl.edge.codec.encode_episode` payload a frame.
``episodes.ack`` (cloud -> edge): ``{"ids": [...]}``, sent once an episode is stored (also for a
duplicate, so the edge stops resending it). ``weights`` (cloud -> edge): one
:func:`~infinirl.edge.codec.encode_weights` payload. ``weights.ack`` (edge -> cloud):
``{"version": v, "digest": d}`` once applied, or ``{"refused": reason}``, after which the cloud sends
the next version in full. The hello of an edge carries ``{"weights_version", "weights_digest"}``,
what it holds, so a reconnecting edge continues with deltas. ``tunnel`` (both ways): TCP
connections from the cloud to services at the edge (:mod:`infinirl.edge.tunnel`).
"""

from __future__ import annotations

import json

__all__ = ["EPISODES", "EPISODE_ACKS", "TUNNEL", "WEIGHTS", "WEIGHT_ACKS", "ProtocolError", "dump", "load",
           "load_episode_ids"]

EPISODES, EPISODE_ACKS = "episodes", "episodes.ack"
WEIGHTS, WEIGHT_ACKS = "weights", "weights.ack"
TUNNEL = "tunnel"


def dump(message: dict) -> bytes:
    return json.dumps(message).encode()


class ProtocolError(ValueError):
    """A message that is not what its stream carries (the peer is broken or not of this version)."""


def load(payload: bytes) -> dict:
    """A message's JSON object; :class:`ProtocolError` for anything else, so a receiver that checks
    its fields need not guard against lists, numbers or bytes that are not JSON."""
    try:
        message = json.loads(payload)
    except ValueError as exc:
        raise ProtocolError(f"a message that is not JSON ({exc}): {bytes(payload[:80])!r}") from None
    if not isinstance(message, dict):
        raise ProtocolError(f"a message that is not a JSON object: {bytes(payload[:80])!r}")
    return message


def load_episode_ids(payload: bytes) -> list[str]:
    """The ids of an ``episodes.ack`` message (:class:`ProtocolError` when it is malformed)."""
    ids = load(payload).get("ids")
    if not isinstance(ids, list) or not all(isinstance(i, str) for i in ids):
        raise ProtocolError(f"an episode acknowledgement without a list of string ids: {bytes(payload[:80])!r}")
    return ids
