"""Toy reward functions for smoke tests and debugging a pipeline (not for real training).

A random tiny model almost never solves a task, so verifiable rewards are all zero and GRPO has
no signal: a pipeline test would pass whether or not training works. These rewards vary with any
output, so advantages are non-zero and weights must move.
"""

from __future__ import annotations


def digit_fraction(response: str, problem) -> float:
    """Fraction of characters that are digits (a smooth, always-defined signal)."""
    return sum(ch.isdigit() for ch in response) / max(1, len(response))


def response_length(response: str, problem) -> float:
    """Length in characters / 100 (for checking overlong shaping and length trends)."""
    return len(response) / 100.0


def uppercase_fraction(response: str, problem) -> float:
    """Fraction of letters that are upper-case: varies a lot across a random model's samples, so
    a GRPO run on a tiny random model has signal from step one (used by the fast learning test)."""
    letters = [ch for ch in response if ch.isalpha()]
    return sum(ch.isupper() for ch in letters) / max(1, len(letters))


def kill_own_process(response: str, problem) -> float:
    """Kills the process that scores (SIGKILL, as the kernel's OOM killer would): for fault-injection
    tests of what a run does when its reward worker dies mid-step."""
    import os
    import signal

    os.kill(os.getpid(), signal.SIGKILL)
    return 0.0
