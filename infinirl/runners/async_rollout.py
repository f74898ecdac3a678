"""The asynchronous core shared by the runners: rollout batches produced ahead of the trainer,
within a staleness bound.

With ``max_staleness`` = η the batch of iteration ``k`` is *submitted* to the rollout side as soon
as the trainer has published weights version ``max(0, k - η)``, and before it publishes the next
version. A rollout rank runs its calls in submission order, so batch ``k`` is produced by exactly
version ``max(0, k - η)`` (its samples carry that version): the schedule, and hence the run, is
deterministic however fast either side is, and a sample is never older than η versions when the
trainer uses it. Producers never wait for the trainer inside that bound; they wait (throttle) only
when they would run more than η versions ahead.

* η = 0 submits batch ``k`` after the weights of step ``k - 1`` are in: the synchronous run, exactly.
* η = 1 generates batch ``k + 1`` while the trainer trains on batch ``k`` (one step off-policy).
* η >= 2 keeps η batches queued on the rollout side, which absorbs slow batches (long tails).

The trainer's loss corrects for the version gap (``algorithm.objective.is_cap``: decoupled PPO's
proximal policy is the trainer's own version at the start of the step, and each token is
reweighted by ``pi_proximal / pi_behaviour``).

Checkpoints: :meth:`RolloutAhead.drain` waits for the batches in flight and returns them with the
ones already done; they are saved with the checkpoint and :meth:`RolloutAhead.restore` puts them
back, so a resumed run uses each sample exactly once, with the version that produced it. Nothing
is produced past the last iteration (that generation would be wasted in every run that is not
extended), so a checkpoint within eta iterations of its run's end lacks the batches past it: a
resume with more ``iterations`` produces them with the resumed weights, fresher than a straight
longer run's, and says so (:meth:`RolloutAhead._warn_unproduced`).
"""

from __future__ import annotations

import os
import pickle
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from infinirl.config import bounded
from infinirl.utils.atomic import atomic_open

#: The batches produced ahead of the trainer, in a checkpoint folder.
AHEAD_BATCHES_FILE = "ahead_batches.pkl"


@dataclass(kw_only=True)
class AsyncConfig:
    """Asynchronous (off-policy) training: rollout runs ahead of the trainer by up to
    ``max_staleness`` weight versions."""

    max_staleness: int | None = bounded(None, ge=0)
    """eta: a batch used at trainer version v was produced by weights version >= v - eta. None
    (default): the synchronous loop. 0: the same run through the asynchronous pipeline (same
    weights, bit for bit). 1: rollout of the next batch overlaps training on this one; 2+: more
    batches queued ahead. Pair eta >= 1 with the off-policy correction: `algorithm.objective.is_cap`
    (reasoning), `algorithm.is_cap` (embodied)."""

    partial_rollout: bool = False
    """Language models, eta >= 1, the hf rollout engine: each weight update reaches the rollout
    ranks at once and interrupts the generations in flight, which go on with the new weights
    (their KV caches rebuilt) instead of finishing with the old ones; every token keeps the
    log-prob and version of the weights that sampled it. Samples are fresher, but where the switch
    falls depends on timing, so runs are no longer bit-reproducible."""


def producing_version(batch: int, max_staleness: int) -> int:
    """The weights version that produces the batch of iteration ``batch`` under the schedule."""
    return max(0, batch - max_staleness)


def partial_rollout_metrics(iteration: int, results) -> dict[str, float]:
    """Per-token staleness and the share of samples a weight update interrupted. Tokens the model
    sampled only: an agent environment's ids between turns (``response_mask`` 0) came from no
    weights and are never trained on."""
    tokens, gaps, interrupted = 0, 0, 0
    for result in results:
        versions = result.response_versions or [result.weight_version] * len(result.response_ids)
        sampled = result.response_mask or [1] * len(versions)
        tokens += sum(sampled)
        gaps += sum(iteration - v for v, m in zip(versions, sampled) if m)
        interrupted += result.response_versions is not None
    return {"async/token_staleness_mean": gaps / max(tokens, 1),
            "async/interrupted_fraction": interrupted / max(len(results), 1)}


def staleness_metrics(iteration: int, versions: list[int]) -> dict[str, float]:
    """How many versions behind the trainer (at ``iteration``) the samples' weights were."""
    gaps = [iteration - version for version in versions]
    return {
        "async/staleness_mean": sum(gaps) / max(len(gaps), 1),
        "async/staleness_max": float(max(gaps, default=0)),
    }


class RolloutAhead:
    """Batches submitted up to ``max_staleness`` iterations ahead of the one being trained.

    ``submit(k)`` starts producing the batch of iteration ``k`` and returns a pending object;
    ``collect(pending)`` waits for it (raising a producer's failure) and returns the batch. The
    caller publishes weights version ``v`` *before* calling :meth:`take` for iteration ``v``,
    which is what fixes each batch's producing version (module doc).
    """

    def __init__(self, max_staleness: int, iterations: int, submit: Callable[[int], Any],
                 collect: Callable[[Any], Any], weights: WeightPusher | None = None):
        if max_staleness < 0:
            raise ValueError(f"max_staleness must be >= 0, got {max_staleness}")
        self.max_staleness, self.iterations = max_staleness, iterations
        self._submit, self._collect, self.weights = submit, collect, weights
        self._pending: dict[int, Any] = {}
        self._ready: dict[int, Any] = {}
        self._restored = False

    def take(self, iteration: int) -> Any:
        """The batch of ``iteration``; first submits every batch the bound now allows."""
        self._fill(iteration)
        if iteration in self._ready:
            return self._ready.pop(iteration)
        return self._collect_batch(iteration, self._pending.pop(iteration))

    def _collect_batch(self, iteration: int, pending: Any) -> Any:
        """``collect``, then the loads of the versions up to the batch's producing one.

        Those loads were queued on every rollout rank before the batch, so they are done: a failed
        one raises its own error here, before the batch is used. A load that failed before copying
        anything leaves the rank on the older version, whole, and the batch would otherwise be
        trained on as if that version were within the bound. When the collection itself failed,
        a failed load is what made it fail (the rank refuses to generate on weights a load tore,
        ``WeightSink.check_weights``): its error is raised instead, with the collection's as context."""
        version = producing_version(iteration, self.max_staleness)
        try:
            batch = self._collect(pending)
        except BaseException:
            if self.weights is not None:
                self.weights.loaded(version, timeout=LOAD_ROOT_CAUSE_WAIT_S, give_up_quietly=True)
            raise
        if self.weights is not None:
            self.weights.loaded(version)
        return batch

    def _fill(self, iteration: int) -> None:
        if self._restored:
            self._restored = False
            self._warn_unproduced(iteration)
        stale = [k for k in (*self._pending, *self._ready) if k < iteration]
        if stale:
            raise RuntimeError(f"batches {sorted(stale)} were produced but never used before iteration {iteration}")
        for k in range(iteration, min(iteration + self.max_staleness + 1, self.iterations)):
            if k not in self._pending and k not in self._ready:
                self._pending[k] = self._submit(k)

    def drain(self) -> dict[int, Any]:
        """Wait for every batch in flight; return all produced, unused batches by iteration."""
        for k in sorted(self._pending):
            self._ready[k] = self._collect_batch(k, self._pending.pop(k))
        return dict(self._ready)

    def settle(self) -> float:
        """Wait for every batch in flight, keeping them for :meth:`take`; the seconds waited.

        Before an evaluation: its requests would queue on the rollout ranks behind these batches
        (a rank runs its calls in submission order), so the evaluation's time would hold generation
        that belongs to training. Waiting changes no batch: each was submitted, and so fixed to its
        producing version, before."""
        start = time.perf_counter()
        self.drain()
        return time.perf_counter() - start

    def restore(self, ready: dict[int, Any]) -> None:
        """Put back the batches a checkpoint saved (see :meth:`drain`). The first :meth:`take`
        then says which batches of its window the checkpoint lacks (:meth:`_warn_unproduced`)."""
        if self._pending:
            raise RuntimeError("restore() with batches in flight")
        self._ready = {int(k): v for k, v in ready.items()}
        self._restored = True

    def _warn_unproduced(self, iteration: int) -> None:
        """A checkpoint of iteration ``c`` holds batches ``c .. c + eta - 1``, each produced by
        version ``k - eta``, except those at or past the ``iterations`` of the run that wrote it,
        which never submitted them. Resumed with more ``iterations``, those batches are produced
        now, by the resumed weights (version ``c``): fresher than a straight run's, so the run is
        not the one a straight run to the new ``iterations`` makes. Said once, on stderr."""
        eta = self.max_staleness
        missing = [k for k in range(iteration, min(iteration + eta, self.iterations)) if k not in self._ready]
        if not missing:
            return
        print(f"infinirl: resuming at iteration {iteration} with max_staleness={eta}: the checkpoint holds no "
              f"batch {', '.join(map(str, missing))} (the run that wrote it ended before producing them ahead), so "
              f"{'they are' if len(missing) > 1 else 'it is'} produced by version {iteration}, not version "
              f"{', '.join(str(producing_version(k, eta)) for k in missing)} as in one run straight to "
              f"iterations={self.iterations}; raising iterations resumes exactly only from a checkpoint at least "
              f"{eta} iterations before the earlier run's end", file=sys.stderr, flush=True)

    @property
    def in_flight(self) -> list[int]:
        return sorted(self._pending)


class WeightPusher:
    """The trainer's weights to the rollout ranks after each update, stamped with the version.

    Synchronous runs wait for the rollout ranks to load them. Asynchronous runs only publish
    (:func:`~infinirl.runtime.start_weight_sync`): each rollout rank loads them after the requests
    queued on it before, which is what fixes every batch's producing version."""

    def __init__(self, trainer, rollout, asynchronous: bool, interrupt: bool = False, changed_only: bool = False):
        self.trainer, self.rollout, self.asynchronous = trainer, rollout, asynchronous
        self.interrupt = interrupt  # partial rollouts: staged beside the running generations
        # After the first push, send only what training changes (a LoRA run's merged layers): the
        # first one makes the rest of every rollout rank's model the trainer's. Not with staging,
        # where a newer version may replace one a rank never loaded.
        self.changed_only = changed_only and not interrupt
        self._sent_full = False
        self._loading: list = []  # published versions the rollout ranks have not loaded yet

    def sent_full(self) -> None:
        """Every rollout rank has loaded a full sync sent around this pusher (a resume's)."""
        self._sent_full = True

    def push(self, version: int) -> float:
        """Send ``version``; the seconds the trainer spent on it."""
        from infinirl.runtime import start_weight_sync, sync_weights

        changed_only, self._sent_full = self.changed_only and self._sent_full, True
        if not self.asynchronous:
            return sync_weights(self.trainer, self.rollout, version=version, changed_only=changed_only).seconds
        self._loading = unfinished_loads(self._loading)  # an earlier load that failed raises its root cause here
        start = time.perf_counter()
        pending = start_weight_sync(self.trainer, self.rollout, version=version, interrupt=self.interrupt,
                                    changed_only=changed_only)
        if self.interrupt:
            # Staged on every rank before the next batch is submitted, so that batch starts on
            # this version (the staleness bound holds); staging does not wait for the generations.
            pending.wait()
        else:
            self._loading.append(pending)
        return time.perf_counter() - start

    def wait(self) -> None:
        """Until every version sent has been loaded (raises a failed load's error). Before an
        evaluation too: it would queue behind those loads on the rollout ranks anyway, and a load
        that failed must stop the run with its own error rather than be evaluated past (on the
        previous version, or refused by a rank whose weights it tore)."""
        for pending in self._loading:
            pending.wait()
        self._loading = []

    def loaded(self, version: int, timeout: float | None = None, give_up_quietly: bool = False) -> None:
        """Until every version up to ``version`` sent has been loaded; raises a failed load's error.
        ``timeout`` per load; ``give_up_quietly``: a load still running then is left to a later
        check instead of raising TimeoutError (a caller that only looks for a root cause)."""
        for pending in [p for p in self._loading if p.version <= version]:
            try:
                pending.wait(timeout)
            except TimeoutError:
                if give_up_quietly:
                    return
                raise
            self._loading.remove(pending)


LOAD_ROOT_CAUSE_WAIT_S = 5.0
"""How long a failed collection waits for the loads queued before it to report their failure."""


def unfinished_loads(loading: list) -> list:
    """The syncs of ``loading`` the rollout ranks have not finished loading; one that finished with
    a failure raises it. Each is asked once whether it is done: one that finishes meanwhile is
    checked at the next call, never dropped unchecked."""
    unfinished = []
    for pending in loading:
        if pending.done():
            pending.wait()
        else:
            unfinished.append(pending)
    return unfinished


def save_ahead_batches(folder: str, batches: dict[int, Any]) -> None:
    with atomic_open(os.path.join(folder, AHEAD_BATCHES_FILE)) as f:
        pickle.dump(batches, f)


def load_ahead_batches(folder: str) -> dict[int, Any]:
    """The batches a checkpoint holds; none if it was written by a synchronous run (the next
    batches are then produced by the resumed weights)."""
    path = os.path.join(folder, AHEAD_BATCHES_FILE)
    if not os.path.exists(path):
        return {}
    with open(path, "rb") as f:
        return pickle.load(f)
