"""Which thread of a process runs its computation (torch, compiled functions).

A script computes on its main thread. A ``Worker`` rank runs its synchronous methods, one at a
time, on one dedicated thread (the main thread runs Ray's event loop); that thread marks itself
when it starts. Why it matters: some torch state is process-wide rather than per thread
(``torch.compiler.set_stance``), and is safe to change only from the one thread that runs compiled
code. Code that changes such state asks :func:`on_compute_thread` first; other threads (ranks
simulated by threads in tests, helper threads) leave it alone.

A rank's constructor runs on its compute thread too, so that one thread does all of the rank's
parallel torch work. Why: torch's intra-op threads are libgomp's (GNU OpenMP), and each thread
that starts a parallel region gets a thread team of its own. Once the teams hold more threads
than the process has cores, libgomp makes *every* waiting thread spin only briefly (not at all
under ``OMP_WAIT_POLICY=PASSIVE``, which workers run with) before it sleeps in the kernel,
whatever ``GOMP_SPINCOUNT`` says. A PPO update is thousands of short parallel regions, so its
helper threads would then sleep and be woken between nearly every pair of them, and the update
slows down after a single parallel op on a second thread
(``python benchmarks/omp_teams.py --repeats 4`` shows the difference on a given machine).
"""

from __future__ import annotations

import threading

__all__ = ["mark_compute_thread", "on_compute_thread"]

_compute_thread_ident: int | None = None


def mark_compute_thread() -> None:
    """Make the calling thread this process's compute thread (instead of the main thread)."""
    global _compute_thread_ident
    _compute_thread_ident = threading.get_ident()


def on_compute_thread() -> bool:
    """True on this process's compute thread: the marked one, else the main thread."""
    marked = _compute_thread_ident
    return threading.get_ident() == (marked if marked is not None else threading.main_thread().ident)
