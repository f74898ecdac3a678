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

__all__ = ["EPISODES", "EPISODE_ACKS", "TUNNEL", "WEIGHTS", "WEIGHT_ACKS", "dump", "load"]

EPISODES, EPISODE_ACKS = "episodes", "episodes.ack"
WEIGHTS, WEIGHT_ACKS = "weights", "weights.ack"
TUNNEL = "tunnel"


def dump(message: dict) -> bytes:
    return json.dumps(message).encode()


def load(payload: bytes) -> dict:
    return json.loads(payload)
