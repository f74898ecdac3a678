"""Per-caller start order for calls to an async Ray actor.

Ray does not promise that an async actor starts calls in the order one caller submitted them, so
callers number their calls (0, 1, 2...) and the actor starts call ``seq`` only after call
``seq - 1`` has taken its turn. A call cancelled while it waits for its turn gives the turn up:
later calls from the same caller never wait behind a call that will not run.

Everything but the wait itself is synchronous, so a cancellation can only land while a call
waits for its turn, never halfway through handing the turn on.
"""

from __future__ import annotations

import asyncio
from collections import defaultdict

__all__ = ["CallOrder"]


class CallOrder:
    """Used from one event loop (an async actor's)."""

    def __init__(self):
        self._next: dict[str, int] = defaultdict(int)
        self._given_up: dict[str, set[int]] = defaultdict(set)
        self._skipped: dict[str, set[int]] = defaultdict(set)
        self._waiting: dict[tuple[str, int], asyncio.Future] = {}

    async def wait_turn(self, caller: str, seq: int, resume: bool = False) -> None:
        """Wait until call ``seq`` of ``caller`` may start. ``resume``: a caller not seen yet
        continues at ``seq`` (a restarted actor picks up the numbering where its caller is).
        Raises ``CancelledError`` for a call its caller gave up (:meth:`skip`) before it arrived."""
        if seq in self._skipped[caller]:
            self._skipped[caller].discard(seq)
            raise asyncio.CancelledError(f"call {seq} was given up by its caller")
        if resume and caller not in self._next:
            self._next[caller] = seq
        self._pass_given_up(caller)  # turns given up before the caller's first call arrived
        if self._next[caller] >= seq:
            # Its turn has passed without it: a call retried after a restart that arrives behind
            # a later one runs at once rather than waiting for a turn that never comes back.
            return
        turn = asyncio.get_running_loop().create_future()
        self._waiting[(caller, seq)] = turn
        try:
            await turn
        except asyncio.CancelledError:  # the turn is given up, now (if it came) or when it comes
            self._waiting.pop((caller, seq), None)
            self._given_up[caller].add(seq)
            self._hand_on(caller)
            raise

    def skip(self, caller: str, seq: int) -> None:
        """The caller gave call ``seq`` up before it reached this actor (Ray could not submit or
        deliver it, or it was cancelled on the way): later calls do not wait for it, and should it
        still arrive it does not run. A call that started, or arrived and waits, is left alone
        (a waiting one gives its own turn up when cancelled).

        A caller with no call here yet gets no numbering from a skip: a restarted actor takes it
        from the caller's next call (``wait_turn(resume=True)``), not from 0."""
        if (caller in self._next and seq < self._next[caller]) or (caller, seq) in self._waiting:
            return
        self._skipped[caller].add(seq)
        self._given_up[caller].add(seq)
        if caller in self._next:
            self._hand_on(caller)

    def end_turn(self, caller: str, seq: int) -> None:
        """Call ``seq`` has started: the next call of ``caller`` may start."""
        if self._next[caller] == seq:
            self._next[caller] = seq + 1
            self._hand_on(caller)

    def _pass_given_up(self, caller: str) -> None:
        given_up = self._given_up[caller]
        while self._next[caller] in given_up:
            given_up.discard(self._next[caller])
            self._next[caller] += 1

    def _hand_on(self, caller: str) -> None:
        self._pass_given_up(caller)
        turn = self._waiting.pop((caller, self._next[caller]), None)
        if turn is not None and not turn.done():
            turn.set_result(None)
