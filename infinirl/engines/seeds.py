"""Sampling seeds of a generation's streamed chunks and of an agent's turns within a chunk.

A generation (one step's rollout) is sampled in chunks, each with a seed derived from its *index*
(:func:`chunk_seed`), so a batch's samples do not depend on how chunks are spread over rollout
ranks. An agent rollout then samples each of its model turns (each generate call) with a seed
derived from its chunk's seed and the turn's number (:func:`turn_seed`).

Why both derivations live here: derived apart, as ``seed + 7919 * index`` for chunks and again
``seed + 7919 * turn`` for turns, chunk 0's turn 1 and chunk 1's turn 0 drew with the same seed
(and so on along every diagonal ``index + turn``): the same random stream for the same batch shape,
i.e. correlated samples. Here every ``(chunk, turn)`` of one generation gets its own seed, by
construction rather than by chance: with ``base`` fixed,

* ``chunk_seed(base, i) = (base + 7919 * i) mod 2**31``, a bijection of ``i`` mod ``2**31`` (7919
  is odd), distinct for every chunk;
* ``turn_seed(chunk_seed(base, i), t) = mix31((base + 7919 * (i + 2**16 * t)) mod 2**31)``: the
  pair ``(i, t)`` is laid out as one index ``i + 2**16 * t``, distinct for ``i < 2**16`` chunks and
  ``t < 2**15`` turns, then mixed by a bijection of ``[0, 2**31)`` (:func:`mix31`), which keeps them
  distinct and spreads neighbouring turns' seeds over the whole range.

Seeds stay below ``2**31`` as before (every engine takes them). Chunk seeds keep their old values, so
runs without an agent sample exactly as they did; an agent's turns sample differently than they did.
Across generations (another ``base``) seeds are distinct only as far as the bases are.
"""

from __future__ import annotations

__all__ = ["SEED_LIMIT", "chunk_seed", "mix31", "turn_seed"]

SEED_LIMIT = 2**31
"""Every derived seed is in ``[0, SEED_LIMIT)``."""
_MASK = SEED_LIMIT - 1
_CHUNK_STRIDE = 7919  # odd: a bijection mod 2**31
_TURN_STRIDE = 2**16  # chunks per generation that never share a turn seed; 2**15 turns per chunk


def mix31(value: int) -> int:
    """A bijection of ``[0, 2**31)`` that scatters neighbouring values (lowbias32's xor-shift-multiply
    rounds on 31 bits). Bijective because each round is: a right xor-shift is undone by repeating it,
    and multiplying by an odd constant has an inverse mod ``2**31``."""
    value &= _MASK
    value ^= value >> 16
    value = (value * 0x7FEB352D) & _MASK
    value ^= value >> 15
    value = (value * 0x046CA68B) & _MASK
    value ^= value >> 16
    return value


def chunk_seed(base: int, index: int) -> int:
    """The seed of chunk ``index`` of a generation sampled with seed ``base``."""
    return (base + _CHUNK_STRIDE * index) % SEED_LIMIT


def turn_seed(chunk: int, turn: int) -> int:
    """The seed of an agent's model turn ``turn`` (0-based generate call) within a chunk sampled with
    seed ``chunk`` (a :func:`chunk_seed`, or the seed of a generation that is not chunked)."""
    return mix31(chunk + _CHUNK_STRIDE * _TURN_STRIDE * turn)
