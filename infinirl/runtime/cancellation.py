"""Cancelling a call that runs on a worker rank's compute thread.

``GroupHandle.cancel()`` cancels the rank's Ray task. An ``async def`` method is cancelled by
asyncio itself; a synchronous method runs on the rank's compute thread, which Python cannot
interrupt. Its host therefore runs it with a ``CancelToken``, and the runtime's own blocking
waits (``Channel`` gets and puts) wait through ``wait_ref``: cancelling the token ends the Ray
call they wait on (by ``ray.cancel``, or by the call's own ``on_cancel``, such as a channel get's
abandon), and they raise ``CallCancelled``, so the compute thread is free for the rank's next
call. Code that blocks elsewhere (a long computation, ``time.sleep``) runs to its end.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import ray

from infinirl.runtime.errors import CallCancelled

__all__ = ["CancelToken", "cancel_quietly", "current_token", "is_cancelled", "run_with_token", "wait_ref"]

_local = threading.local()


class CancelToken:
    """The cancel state of one running call, and the Ray calls it is waiting on."""

    def __init__(self, label: str):
        self.label = label
        self.cancelled = False
        self._refs: dict = {}  # ref -> how to end it when cancelled
        self._lock = threading.Lock()

    def cancel(self) -> None:
        with self._lock:
            self.cancelled = True
            enders = list(self._refs.values())
        for end in enders:
            end()

    def track(self, ref, on_cancel: Callable[[], Any] | None = None) -> None:
        end = on_cancel or (lambda: cancel_quietly(ref))
        with self._lock:
            self._refs[ref] = end
            cancelled = self.cancelled
        if cancelled:
            end()

    def untrack(self, ref) -> None:
        with self._lock:
            self._refs.pop(ref, None)


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


def is_cancelled() -> bool:
    """Whether the call running on this thread has been cancelled."""
    token = current_token()
    return token is not None and token.cancelled


# Ray cancels the calls a cancelled call makes, and can lose the reply of an actor call it cancels
# in a race (ray-project/ray#46157); so a waiter that sees its call cancelled repeats the cancel
# (``on_cancel``, or ``ray.cancel``) from its own thread, then waits at most CANCELLED_WAIT_S.
CANCELLED_WAIT_S = 30.0
WAIT_SLICE_S = 1.0


def wait_ref(ref, on_cancel: Callable[[], Any] | None = None, cancelled_wait_s: float | None = None) -> Any:
    """``ray.get(ref)``, which a cancel of the current call interrupts with ``CallCancelled``.
    The cancel ends the call by ``ray.cancel(ref)``, or by ``on_cancel()`` when given (then the
    call itself ends soon after, and its result or error comes back as usual). Once cancelled, the
    wait repeats the cancel and lasts at most ``cancelled_wait_s`` (default ``CANCELLED_WAIT_S``)
    more, so a reply Ray loses cannot hang the rank."""
    token = current_token()
    if token is None:
        return ray.get(ref)
    token.track(ref, on_cancel)
    give_up_at = None
    try:
        while True:
            try:
                return ray.get(ref, timeout=WAIT_SLICE_S)
            except ray.exceptions.GetTimeoutError:
                if not token.cancelled:
                    continue
                if give_up_at is None:
                    (on_cancel or (lambda: cancel_quietly(ref)))()
                    limit = CANCELLED_WAIT_S if cancelled_wait_s is None else cancelled_wait_s
                    give_up_at = time.monotonic() + limit
                elif time.monotonic() > give_up_at:
                    raise cancelled_error() from None
            except ray.exceptions.TaskCancelledError:
                if token.cancelled:
                    raise cancelled_error() from None
                raise
    finally:
        token.untrack(ref)


def cancel_quietly(ref) -> None:
    """``ray.cancel(ref)``, for a call that may have finished already."""
    try:
        ray.cancel(ref)
    except Exception:
        pass  # finished already, or its actor is gone: nothing left to cancel


def cancelled_error() -> CallCancelled:
    """The error that ends the current call once it has been cancelled."""
    token = current_token()
    return CallCancelled(f"{token.label if token else 'the call'} was cancelled")
