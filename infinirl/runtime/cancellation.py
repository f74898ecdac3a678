"""Cancelling a call that runs on a worker rank's compute thread.

``GroupHandle.cancel()`` cancels the rank's Ray task. An ``async def`` method is cancelled by
asyncio itself; a synchronous method runs on the rank's compute thread, which Python cannot
interrupt. Its host therefore runs it with a ``CancelToken``, and the runtime's own blocking
waits (``Channel`` gets and puts) wait through ``wait_ref``: cancelling the token cancels the Ray
call they wait on, and they raise ``CallCancelled`` at once, so the compute thread is free for the
rank's next call. Code that blocks elsewhere (a long computation, ``time.sleep``) runs to its end.
"""

from __future__ import annotations

import threading
from typing import Any

import ray

from infinirl.runtime.errors import CallCancelled

__all__ = ["CancelToken", "cancel_quietly", "current_token", "run_with_token", "wait_ref"]

_local = threading.local()


class CancelToken:
    """The cancel state of one running call, and the Ray calls it is waiting on."""

    def __init__(self, label: str):
        self.label = label
        self.cancelled = False
        self._refs: set = set()
        self._lock = threading.Lock()

    def cancel(self) -> None:
        with self._lock:
            self.cancelled = True
            refs = list(self._refs)
        for ref in refs:
            cancel_quietly(ref)

    def track(self, ref) -> None:
        with self._lock:
            self._refs.add(ref)
            cancelled = self.cancelled
        if cancelled:
            cancel_quietly(ref)

    def untrack(self, ref) -> None:
        with self._lock:
            self._refs.discard(ref)


def current_token() -> CancelToken | None:
    """The token of the call running on this thread (None outside a rank's synchronous call)."""
    return getattr(_local, "token", None)


def run_with_token(token: CancelToken, fn, args: tuple, kwargs: dict) -> Any:
    """Run ``fn(*args, **kwargs)`` with ``token`` as this thread's current token."""
    _local.token = token
    try:
        return fn(*args, **kwargs)
    finally:
        _local.token = None


def wait_ref(ref) -> Any:
    """``ray.get(ref)``, which a cancel of the current call interrupts with ``CallCancelled``."""
    token = current_token()
    if token is None:
        return ray.get(ref)
    token.track(ref)
    try:
        return ray.get(ref)
    except ray.exceptions.TaskCancelledError:
        if token.cancelled:
            raise CallCancelled(f"{token.label} was cancelled") from None
        raise
    finally:
        token.untrack(ref)


def cancel_quietly(ref) -> None:
    """``ray.cancel(ref)``, for a call that may have finished already."""
    try:
        ray.cancel(ref)
    except Exception:
        pass  # finished already, or its actor is gone: nothing left to cancel
