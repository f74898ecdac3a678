"""The link's outgoing frames, one queue per stream, taken in deficit round-robin.

Streams share one connection, and a frame goes on the wire whole, so a stream with a backlog of
large frames (episodes with camera frames) would make every small message queued behind it
(weight announcements, robot call replies, acknowledgements, heartbeats) wait for the whole
backlog. :class:`FairQueue` keeps each stream's frames in order and takes the next frame from the
streams in turn, each turn granting ``quantum`` bytes of credit (deficit round-robin): a stream
sends frames while its credit covers them. So a small frame queued on an idle stream goes out after
at most the frame being written and, from each other busy stream, one turn's frames (one frame when
its frames are larger than ``quantum``, at most ``quantum`` bytes of smaller ones); and busy
streams share the bytes of the connection evenly whatever their frame sizes. Not thread-safe: the link guards it.
"""

from __future__ import annotations

import collections
import math

__all__ = ["FairQueue"]


class FairQueue:
    """Frames by stream (see the module docstring); ``quantum``: bytes of credit per turn."""

    def __init__(self, quantum: int = 1 << 16) -> None:
        if quantum < 1:
            raise ValueError(f"fair queue quantum must be >= 1 byte, got {quantum}")
        self.quantum = quantum
        self.bytes = 0
        self._queues: dict[str, collections.deque] = {}
        self._credit: dict[str, int] = {}
        self._turns: collections.deque[str] = collections.deque()  # streams with frames, the one in turn first
        self._granted = False  # the stream in turn got its quantum

    def __len__(self) -> int:
        return sum(len(queue) for queue in self._queues.values())

    def __bool__(self) -> bool:
        return bool(self._turns)

    def push(self, stream: str, frame) -> None:
        queue = self._queues.setdefault(stream, collections.deque())
        if not queue:
            self._turns.append(stream)
            self._credit[stream] = 0
        queue.append(frame)
        self.bytes += len(frame)

    def pop(self) -> tuple[str, object] | None:
        """``(stream, frame)`` of the next frame to send, or None when nothing is queued."""
        idle = 0  # turns in a row that sent nothing
        while self._turns:
            stream = self._turns[0]
            queue = self._queues[stream]
            if not self._granted:  # the front stream's turn begins
                self._credit[stream] += self.quantum
                self._granted = True
            if self._credit[stream] >= len(queue[0]):
                return stream, self._take(stream, queue)
            self._turns.rotate(-1)  # its turn ends; it keeps its credit for the next one
            self._granted = False
            idle += 1
            if idle == len(self._turns):
                self._skip_idle_rounds()
                idle = 0
        return None

    def _take(self, stream: str, queue: collections.deque):
        frame = queue.popleft()
        self.bytes -= len(frame)
        self._credit[stream] -= len(frame)
        if not queue:  # an emptied stream keeps no credit (it would burst when it comes back)
            self._turns.popleft()
            self._credit[stream] = 0
            self._granted = False
        return frame

    def _skip_idle_rounds(self) -> None:
        """A round in which no stream could send: grant at once the rounds before one can (the same
        choice as going round that many times, without the loop)."""
        rounds = min(math.ceil((len(self._queues[s][0]) - self._credit[s]) / self.quantum) for s in self._turns)
        # the next round grants one quantum more to each, so `rounds - 1` are skipped
        if rounds > 1:
            for stream in self._turns:
                self._credit[stream] += (rounds - 1) * self.quantum
