"""Sampling seeds of streamed chunks and agent turns: every (chunk, turn) of a generation gets its
own seed, deterministically, below 2**31, and the chunk seeds of runs without an agent are the old ones."""

import random

import pytest

from infinirl.engines.seeds import SEED_LIMIT, chunk_seed, mix31, turn_seed

BASES = [0, 1, 7919, 123_456_789, SEED_LIMIT - 1]


def unmix31(value: int) -> int:
    """The inverse of :func:`mix31`, round by round (which is what makes it a bijection)."""
    mask = SEED_LIMIT - 1

    def unshift(x: int, s: int) -> int:  # x ^= x >> s, undone by repeating it until the shifts run out
        result = x
        for _ in range(31 // s):
            result = x ^ (result >> s)
        return result

    value = unshift(value, 16)
    value = (value * pow(0x046CA68B, -1, SEED_LIMIT)) & mask
    value = unshift(value, 15)
    value = (value * pow(0x7FEB352D, -1, SEED_LIMIT)) & mask
    return unshift(value, 16)


@pytest.mark.parametrize("base", BASES)
def test_every_chunk_and_turn_of_a_generation_has_its_own_seed(base):
    chunks, turns = 512, 64
    seeds = [turn_seed(chunk_seed(base, i), t) for i in range(chunks) for t in range(turns)]
    assert len(set(seeds)) == chunks * turns
    assert all(0 <= seed < SEED_LIMIT for seed in seeds)
    # the diagonal the old derivation (seed + 7919 * index, then + 7919 * turn) put on one seed
    assert turn_seed(chunk_seed(base, 0), 1) != turn_seed(chunk_seed(base, 1), 0)
    # the far edges of the guaranteed range: 2**16 chunks, 2**15 turns
    edge = {turn_seed(chunk_seed(base, i), t) for i in (0, 1, 2**16 - 1) for t in (0, 1, 2**15 - 1)}
    assert len(edge) == 9


def test_seeds_are_deterministic_and_chunk_seeds_keep_their_old_values():
    # pinned: a change of the derivation changes every agent run's samples, so it shows here first
    # (pure integer arithmetic: the same on every host and in every process)
    assert [turn_seed(chunk_seed(100, i), t) for i in range(2) for t in range(3)] == [
        570832929, 1902895142, 599691380, 1027735335, 1313789504, 1648270513]
    assert turn_seed(100, 0) == mix31(100)
    # runs without an agent sample their chunks with the seeds they always had
    for base in BASES:
        for index in (0, 1, 5, 1000):
            assert chunk_seed(base, index) == (base + 7919 * index) % (2**31)


def test_mix31_is_a_bijection_of_31_bits():
    rng = random.Random(0)
    values = [0, 1, SEED_LIMIT - 1, *(rng.randrange(SEED_LIMIT) for _ in range(2000))]
    for value in values:
        mixed = mix31(value)
        assert 0 <= mixed < SEED_LIMIT and unmix31(mixed) == value
    # neighbouring inputs land far apart (the turn seeds of one chunk are not an arithmetic run)
    assert len({mix31(v) >> 24 for v in range(64)}) > 32
