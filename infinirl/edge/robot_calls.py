"""Calls from the cloud's trainer to the robot at the edge, over the link: describe, start, stats,
evaluate, demonstrations, stop, close.

The trainer drives a robot at the edge the way it drives a Ray robot worker, by named calls. A call
is one JSON frame on ``robot.call`` (cloud to edge: ``{"id", "method", "args"}``); its answer is one
JSON frame on ``robot.reply`` (``{"id", "result", "error", "episodes": k}``) followed by ``k``
episode frames (:func:`~infinirl.edge.codec.encode_episode`; the demonstrations a call recorded).
Answers are JSON and episodes, never pickles: the cloud runs nothing an edge sends. Episode frames
are named after their call (``reply-<id>-<index>``); the caller skips the episode frames of an answer
it gave up waiting for, and turns a reply it cannot read into a :class:`RobotCallError`.

:class:`RobotCaller` (cloud) makes one call at a time on the edge's present link; when the link
drops during a call, it repeats the call on the next link (the calls are safe to repeat: ``start``
and ``stop`` are idempotent, a repeated ``stats`` loses at most one window's episode summaries).
:class:`RobotCallServer` (edge) answers calls on a thread of its own with a table of handlers.
"""

from __future__ import annotations

import io
import json
import logging
import threading
import time
from collections.abc import Callable, Mapping

import numpy as np

from infinirl.edge.codec import check_episode_file, decode_episode, encode_episode
from infinirl.edge.link import LinkError

__all__ = ["ROBOT_CALLS", "ROBOT_REPLIES", "RobotCallError", "RobotCallServer", "RobotCaller"]

logger = logging.getLogger(__name__)

ROBOT_CALLS, ROBOT_REPLIES = "robot.call", "robot.reply"
_POLL_S = 0.1

Handler = Callable[..., tuple[object, list]]
"""``handler(*args) -> (JSON-able result, episodes)``."""


class RobotCallError(RuntimeError):
    """A call failed at the edge (the edge's error, one line) or found no edge within its timeout."""


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON-able")


def _dump(message: dict) -> bytes:
    return json.dumps(message, default=_plain).encode()


class RobotCaller:
    """Calls on the robot of edge ``edge`` through ``hub`` (a :class:`~infinirl.edge.cloud_hub.CloudHub`);
    while the edge is not connected, ``check()`` may raise the reason it will not come back."""

    def __init__(self, hub, edge: str, check: Callable[[], None] | None = None) -> None:
        self.hub, self.edge, self.check = hub, edge, check  # check(): raises when the edge cannot come back
        self._lock = threading.Lock()
        self._next_id = 0

    def call(self, method: str, *args, timeout: float = 120.0) -> tuple[object, list[dict]]:
        """``(result, episodes)`` of ``method(*args)`` at the edge; :class:`RobotCallError` when the
        edge reports a failure or no answer came within ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        with self._lock:
            self._next_id += 1
            call_id = self._next_id
            payload = _dump({"id": call_id, "method": method, "args": list(args)})
            while True:
                link = self.hub.link(self.edge)
                if link is None:
                    if self.check is not None:
                        self.check()
                    if time.monotonic() >= deadline:
                        raise RobotCallError(f"robot call {method!r}: edge {self.edge} not connected within "
                                             f"{timeout:.0f} s")
                    time.sleep(_POLL_S)
                    continue
                try:
                    return self._exchange(link, call_id, method, payload, deadline)
                except LinkError as exc:  # the link dropped: repeat the call on the next one
                    logger.info("robot call %r to edge %s: link dropped (%s); repeating it", method, self.edge, exc)
                except TimeoutError:
                    raise RobotCallError(f"robot call {method!r}: edge {self.edge} gave no answer within "
                                         f"{timeout:.0f} s") from None

    def _exchange(self, link, call_id: int, method: str, payload: bytes, deadline: float):
        def receive() -> bytes:
            return link.recv(ROBOT_REPLIES, timeout=max(deadline - time.monotonic(), 0.01))

        link.send(ROBOT_CALLS, payload, timeout=max(deadline - time.monotonic(), 0.01))
        while True:
            frame = receive()
            if _is_episode(frame):  # the rest of an answer whose call timed out partway through its episodes
                continue
            header = self._header(frame, method)
            if header["id"] != call_id:  # the answer to a call that timed out before: not ours
                for _ in range(header["episodes"]):
                    receive()
                continue
            episodes = []
            for index in range(header["episodes"]):
                episodes.append(self._episode(receive(), f"reply-{call_id}-{index}", method))
            if header.get("error"):
                raise RobotCallError(f"edge {self.edge}: robot call {method!r} failed: {header['error']}")
            return header.get("result"), episodes

    def _header(self, frame: bytes, method: str) -> dict:
        try:
            header = json.loads(frame)
        except ValueError as exc:
            header, problem = None, f"not JSON ({exc})"
        else:
            problem = "not a JSON object with an id and an episode count"
        if not (isinstance(header, dict) and "id" in header and isinstance(header.get("episodes", 0), int)):
            raise RobotCallError(f"edge {self.edge}: robot call {method!r}: unreadable reply ({problem}): "
                                 f"{bytes(frame[:80])!r}")
        return {**header, "episodes": header.get("episodes", 0)}

    def _episode(self, frame: bytes, expected: str, method: str) -> dict:
        try:
            episode_id, episode = decode_episode(frame)
        except Exception as exc:  # the frame is the only input: whatever fails, it is not an episode
            raise RobotCallError(f"edge {self.edge}: robot call {method!r}: an episode of its answer could not be "
                                 f"decoded ({exc!r})") from None
        if episode_id != expected:
            raise RobotCallError(f"edge {self.edge}: robot call {method!r}: got episode {episode_id!r} where "
                                 f"{expected!r} belongs")
        return episode


def _is_episode(frame: bytes) -> bool:
    try:
        check_episode_file(io.BytesIO(frame), len(frame))
    except ValueError:
        return False
    return True


class RobotCallServer:
    """Answers the cloud's robot calls at the edge: ``client`` is the
    :class:`~infinirl.edge.edge_client.EdgeClient`, ``handlers`` maps method names to handlers."""

    def __init__(self, client, handlers: Mapping[str, Handler], *, send_timeout_s: float = 60.0) -> None:
        self.client, self.handlers, self.send_timeout_s = client, dict(handlers), send_timeout_s
        self.calls = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="edge-robot-calls", daemon=True)

    def start(self) -> RobotCallServer:
        self._thread.start()
        return self

    def close(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self._thread.join(timeout)

    def _run(self) -> None:
        while not self._stop.is_set():
            link = self.client.link
            if link is None:
                self._stop.wait(_POLL_S)
                continue
            try:
                payload = link.recv(ROBOT_CALLS, timeout=_POLL_S * 5)
            except TimeoutError:
                continue
            except LinkError:
                continue
            try:
                call = json.loads(payload)
            except ValueError:
                call = None
            if not isinstance(call, dict):  # answered nowhere: without an id the cloud could not match it
                logger.warning("robot calls: ignored a call that is not a JSON object: %r", payload[:80])
                continue
            self._answer(link, call)

    def _answer(self, link, call: dict) -> None:
        self.calls += 1
        handler = self.handlers.get(call.get("method"))
        result, episodes, error = None, [], None
        if handler is None:
            error = f"unknown method {call.get('method')!r}; known: {', '.join(sorted(self.handlers))}"
        else:
            try:
                result, episodes = handler(*call.get("args", []))
            except Exception as exc:  # reported to the cloud in one line, and logged here in full
                logger.exception("robot call %r failed", call.get("method"))
                error = f"{type(exc).__name__}: {exc}"
        try:
            link.send(ROBOT_REPLIES, _dump({"id": call.get("id"), "result": result, "error": error,
                                            "episodes": len(episodes)}), timeout=self.send_timeout_s)
            for index, episode in enumerate(episodes):
                link.send(ROBOT_REPLIES, encode_episode(episode, episode_id=f"reply-{call.get('id')}-{index}"),
                          timeout=self.send_timeout_s)
        except (LinkError, TimeoutError) as exc:  # the cloud repeats the call on the next link
            logger.info("robot call %r: answer not sent (%s)", call.get("method"), exc)
