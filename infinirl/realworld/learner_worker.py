"""The real-world learner: SAC updates from a persistent replay store, weights published by version.

:class:`RealWorldLearnerWorker` owns a :class:`~infinirl.components.sac_learner.SACAgent` and the
run's :class:`~infinirl.realworld.replay.ReplayStore` (on disk under the run's output folder, so no
episode that reached the learner is lost by a crash), and optionally a second store of
demonstrations (RLPD: each mini-batch is ``demo_fraction`` demonstrations, the rest online data).
With ``interventions_as_demos``, every run of steps a human acted in (``intervened``) is also
appended to the demonstrations store as an episode of its own
(:func:`~infinirl.realworld.intervention.segments.intervened_segments`), before the episode itself
and, for an episode with a sender's id, under ids derived from it, so a crash between the two
appends loses neither when the sender resends. With a pixel encoder
(``SACNetSpec.encoder="cnn"``) the mini-batches carry the frames of the cameras it reads besides the
state; the agent computes on ``device`` (``auto``: the GPU of the rank's placement) and the published
weights are host copies.

* **asynchronous** (:meth:`start`): an ingest thread takes the episodes the robots put on the
  channel and appends them to the store; a training thread updates continuously once
  ``learning_starts`` transitions are stored, never waiting for new data (``max_updates_per_step`` optionally caps the
  updates per stored transition). Every ``publish_every`` updates it snapshots the actor as a new
  version; the driver moves the newest snapshot to the robots (:meth:`weights_for_sync`);
* **synchronous** (:meth:`add_and_update`): the same ingest and update code, called by the driver
  between collections.

**Committed ids.** An episode may carry a sender's id for it under :data:`SOURCE_ID` (the edge
transport's episode id). It is appended to the store with that id, so a resend is stored once
(:meth:`~infinirl.realworld.replay.ReplayStore.append`), and once it is committed (or deliberately
dropped as stale, or found stored already) its id is put on the channel under
:func:`committed_key` ``(key)`` (``{"ids": [...]}``), where the sender's side reads which episodes it
may forget (the edge's spool keeps each episode until then).

**Staleness.** When an episode arrives, the lag of each policy step is the number of versions
published since the one that chose it. With ``max_staleness`` set, an episode whose largest lag
exceeds it is dropped (``staleness_action="drop"``, counted) or kept and only counted (``"log"``).

**Checkpoints** hold the agent (weights, optimisers, generator, update count), the store's sampler
state and the version; the store itself is already on disk and is reopened on resume, with every
episode appended after the checkpoint still in it (and folded into the state statistics and the
counts on loading, as its ingest did). A learner that starts without a checkpoint on stores an
earlier run left folds every stored episode into the state statistics instead (:meth:`observe_stored`).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import defaultdict
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from infinirl.components.embodied_policy import compute_device
from infinirl.components.sac_learner import SACAgent, SACNetSpec, SACUpdateSpec
from infinirl.models.sac_encoders import PIXELS_PREFIX
from infinirl.realworld.episodes import episode_spec, staleness_of
from infinirl.realworld.intervention.segments import intervened_segments
from infinirl.realworld.replay import ReplayStore, SamplingSpec, StoreOptions
from infinirl.realworld.robot_worker import VERSION_TENSOR, unit_box
from infinirl.runtime import ChannelClosed, ChannelError, WeightSource, Worker
from infinirl.utils.atomic import torch_save_atomic

__all__ = ["SOURCE_ID", "LearnerLoopSpec", "RealWorldLearnerWorker", "committed_key"]

logger = logging.getLogger(__name__)

_CHECKPOINT = "learner.pt"
_TAKE_ALL = 1e12  # channel weight target: every waiting episode
_INGEST_WAIT_S = 0.1  # one look for episodes gathers what arrives within this
_IDLE_WAIT_S = 0.02  # nothing to update yet: how long the training thread waits before it looks again
_REPORT_TIMEOUT_S = 60.0

SOURCE_ID = "source_id"
"""The key of an episode's sender id (a string; not stored as a field, but as the store's source id)."""


def committed_key(key: str) -> str:
    """The channel key on which the learner reports the sender ids of the episodes it took from ``key``."""
    return f"{key}.committed"


@dataclass(frozen=True, kw_only=True)
class LearnerLoopSpec:
    """How the learner trains between the robots (documented on the runner's config fields)."""

    replay_dir: str
    demo_dir: str | None = None
    demo_fraction: float = 0.0
    learning_starts: int = 500
    publish_every: int = 20
    max_staleness: int | None = None
    staleness_action: Literal["drop", "log"] = "drop"
    max_updates_per_step: float | None = None
    durable: bool = True
    cameras: dict | None = None
    interventions: bool = False
    """The robots record ``intervened`` (they have an intervention device)."""
    interventions_as_demos: bool = False
    """Intervened stretches also go into the demonstrations store (needs ``demo_dir``)."""


class RealWorldLearnerWorker(Worker, WeightSource):
    """SAC on a persistent replay store (see the module docstring)."""

    def __init__(self, net: SACNetSpec, update: SACUpdateSpec, loop: LearnerLoopSpec, obs_dim: int, action_dim: int,
                 num_threads: int = 1, device: str = "cpu", action_mask=None, embodiments: int = 1):
        if num_threads:
            torch.set_num_threads(num_threads)
        torch.set_flush_denormal(True)  # see SACLearnerWorker: denormals take a slow path on x86
        self.loop, self.spec = loop, update
        # auto: the GPU the placement gives this rank, else the CPU (a conv encoder wants the GPU).
        self.compute = compute_device(self.device if device == "auto" else "cpu", device)
        # action_mask (robots of different action sizes): see control_loop.EmbodimentActionMask;
        # embodiments: robot kinds sharing the policy (the state normaliser keeps statistics per kind).
        self.agent = SACAgent(net, update, obs_dim, unit_box(action_dim), self.compute, cameras=loop.cameras,
                              action_mask=action_mask, embodiments=embodiments)
        encoder = getattr(self.agent.actor, "encoder", None)
        # The camera fields the networks read (none for the state encoder, which reads only the state).
        self._pixel_keys = [PIXELS_PREFIX + name for name in getattr(encoder, "cameras", {})]
        if loop.interventions_as_demos and (loop.demo_dir is None or not loop.interventions):
            raise ValueError("LearnerLoopSpec.interventions_as_demos needs interventions=True and a demo_dir")
        fields = episode_spec(obs_dim, action_dim, loop.cameras, interventions=loop.interventions)
        options = StoreOptions(durable=loop.durable)
        self.store = ReplayStore(loop.replay_dir, fields, options=options,
                                 sampling=SamplingSpec(seed=int(np.random.SeedSequence([update.seed, 0x5A]).
                                                                generate_state(1)[0])))
        self.demos = None
        if loop.demo_dir is not None:
            self.demos = ReplayStore(loop.demo_dir, fields, options=options,
                                     sampling=SamplingSpec(seed=int(np.random.SeedSequence([update.seed, 0xDE]).
                                                                    generate_state(1)[0])))
        self.version = 0
        self._snapshot = self._snap()
        self._lock = threading.RLock()  # one of: an update, an ingest, a checkpoint, a snapshot read
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._channel = None
        self._error: BaseException | None = None
        self._counts: dict[str, float] = defaultdict(float)
        self._metric_sums: dict[str, float] = defaultdict(float)
        self._metric_counts: dict[str, int] = defaultdict(int)
        self._updates_reported = 0
        self._reported_at = time.perf_counter()
        # Whether the state statistics hold what the stores held when they were opened (a checkpoint's
        # do, and so does :meth:`observe_stored`); from the first episode stored, folding them all would
        # count that one twice.
        self._stored_observed = False

    # ---------------------------------------------------------------- data in
    def _ingest(self, episodes: list[dict]) -> list[str]:
        """Store ``episodes``; returns the sender ids (:data:`SOURCE_ID`) of those that carried one,
        each now committed, dropped as stale, or found stored already."""
        handled = []
        with self._lock:
            for episode in episodes:
                source = episode.get(SOURCE_ID)
                if source is not None:
                    episode = {key: value for key, value in episode.items() if key != SOURCE_ID}
                    handled.append(source)
                    if self.store.episode_of_source(source) is not None:  # a resend of a stored episode
                        self._counts["duplicate_episodes"] += 1
                        continue
                self._store_one(episode, source)
        return handled

    def _store_one(self, episode: dict, source: str | None) -> None:
        self._stored_observed = True
        lag = staleness_of(episode["version"], self.version)
        self._counts["policy_steps"] += lag.policy_steps
        self._counts["lag_sum"] += lag.lag_sum
        self._counts["lag_max"] = max(self._counts["lag_max"], lag.lag_max)
        if lag.exceeds(self.loop.max_staleness):
            self._counts["stale_episodes"] += 1
            self._counts["stale_steps"] += len(episode["action"])
            if self.loop.staleness_action == "drop":
                self._counts["dropped_episodes"] += 1
                self._counts["dropped_steps"] += len(episode["action"])
                return
        if self.loop.interventions_as_demos:
            # Before the episode itself: the resend of an episode whose main append a crash cut off
            # reaches this line again, and the segments' own source ids make their appends once-only.
            for index, segment in enumerate(intervened_segments(episode)):
                segment_source = None if source is None else f"{source}#intervention{index}"
                if segment_source is None or self.demos.episode_of_source(segment_source) is None:
                    self.demos.append(segment, source_id=segment_source)
                    self._counts["intervention_demo_steps"] += len(segment["action"])
        self.store.append(episode, source_id=source)
        self.agent.observe_states(episode["state"])
        self._counts["episodes"] += 1
        self._counts["steps"] += len(episode["action"])

    def _report_committed(self, channel, key: str, handled: list[str]) -> None:
        """Tell the sender's side which episodes it may forget (a report that cannot be put is
        logged: the sender resends those episodes and the store recognises them)."""
        if not handled:
            return
        try:
            channel.put({"ids": handled}, key=committed_key(key), timeout=_REPORT_TIMEOUT_S)
        except (TimeoutError, ChannelClosed, ChannelError) as exc:
            logger.warning("could not report %d committed episode ids on %r (%r); their sender resends them",
                           len(handled), committed_key(key), exc)

    def add_demonstrations(self, episodes: list[dict]) -> int:
        """Append demonstrations to the demo store; returns how many it holds."""
        if self.demos is None:
            raise RuntimeError("this learner has no demonstrations store (demos are off in the config)")
        with self._lock:
            self._stored_observed = True
            for episode in episodes:
                self.demos.append(episode)
                self.agent.observe_states(episode["state"])
            return self.demos.num_episodes

    def demo_episodes(self) -> int:
        return 0 if self.demos is None else self.demos.num_episodes

    # ---------------------------------------------------------------- updates
    def _can_update(self) -> bool:
        if len(self.store) < max(self.loop.learning_starts, 1):
            return False
        cap = self.loop.max_updates_per_step
        return cap is None or self.agent.updates < cap * len(self.store)

    def _sample(self) -> dict[str, torch.Tensor]:
        size = self.spec.batch_size
        n_demo = int(round(size * self.loop.demo_fraction)) if self.demos is not None and len(self.demos) else 0
        parts = [self.store.sample(size - n_demo)]
        if n_demo:
            parts.append(self.demos.sample(n_demo))
        rows = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
        return {"obs": self._observations(rows, "obs"), "next_obs": self._observations(rows, "next_obs"),
                "action": self._tensor(rows["action"]), "reward": self._tensor(rows["reward"]),
                "terminated": self._tensor(rows["terminated"])}

    def _tensor(self, rows: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(rows).to(self.compute)  # on the CPU: the array itself, no copy

    def _observations(self, rows: dict[str, np.ndarray], prefix: str):
        """The state rows, or with a pixel encoder the state and the frames it reads (uint8)."""
        state = self._tensor(rows[f"{prefix}.state"])
        if not self._pixel_keys:
            return state
        return {"state": state, **{key: self._tensor(rows[f"{prefix}.{key}"]) for key in self._pixel_keys}}

    def _update_once(self) -> None:
        with self._lock:
            metrics = self.agent.update(self._sample())
            for key, value in metrics.items():
                self._metric_sums[key] += float(value)
                self._metric_counts[key] += 1
            if self.agent.updates % self.loop.publish_every == 0:
                self.publish()

    def _snap(self) -> list[tuple[str, torch.Tensor]]:
        # Host copies: the robots load them on their CPUs, whatever device the learner computes on.
        state = [(name, tensor.detach().to("cpu", copy=True)) for name, tensor in self.agent.actor.state_dict().items()]
        return [*state, (VERSION_TENSOR, torch.tensor([self.version], dtype=torch.int64))]

    def add_and_update(self, episodes: list[dict], num_updates: int, publish: bool = False) -> int:
        """Synchronous mode: store ``episodes``, then run up to ``num_updates`` updates (none before
        ``learning_starts``); with ``publish``, the actor after them becomes a new version (the
        next collection uses exactly these weights). Returns the published version (the metrics
        accumulate for :meth:`status`)."""
        self._ingest(episodes)
        done = 0
        for _ in range(num_updates):
            if len(self.store) < max(self.loop.learning_starts, 1):
                break
            self._update_once()
            done += 1
        if publish and done:
            self.publish()
        return self.version

    def publish(self) -> int:
        """Snapshot the actor as a new version now; returns the version."""
        with self._lock:
            self.version += 1
            self._snapshot = self._snap()
            return self.version

    def published_version(self) -> int:
        return self.version

    # ---------------------------------------------------------------- asynchronous
    def start(self, channel, key: str = "episodes") -> None:
        """Train on a thread of its own while an ingest thread stores what arrives on ``channel``."""
        if self._threads:
            return
        self._stop.clear()
        self._channel = (channel, key)
        self._threads = [threading.Thread(target=self._guarded, args=(self._ingest_loop, channel, key),
                                          name="learner-ingest", daemon=True),
                         threading.Thread(target=self._guarded, args=(self._train_loop,), name="learner-train",
                                          daemon=True)]
        for thread in self._threads:
            thread.start()

    def _guarded(self, loop, *args) -> None:
        try:
            loop(*args)
        except BaseException as exc:
            logger.exception("learner thread %s failed", threading.current_thread().name)
            self._error = self._error or exc
            self._stop.set()

    def _ingest_loop(self, channel, key: str) -> None:
        while not self._stop.is_set():
            try:  # every episode waiting, and those arriving within the wait
                episodes = channel.get_batch(_TAKE_ALL, key=key, timeout=_INGEST_WAIT_S)
            except TimeoutError:
                continue
            except ChannelClosed:
                return
            self._report_committed(channel, key, self._ingest(episodes))

    def _train_loop(self) -> None:
        while not self._stop.is_set():
            if self._can_update():
                self._update_once()
            else:
                self._stop.wait(_IDLE_WAIT_S)

    def stop(self) -> dict:
        self._stop.set()
        for thread in self._threads:
            thread.join(60.0)
        self._threads = []
        if self._channel is not None:  # what the robots sent before they stopped is stored, not lost
            channel, key = self._channel
            self._channel = None
            try:
                self._report_committed(channel, key,
                                       self._ingest(channel.get_batch(_TAKE_ALL, key=key, timeout=_INGEST_WAIT_S)))
            except (TimeoutError, ChannelClosed):
                pass
        return self.status()

    # ---------------------------------------------------------------- reporting
    def status(self) -> dict:
        """Version, counters and the updates' mean metrics since the last call."""
        if self._error is not None:
            raise RuntimeError(f"learner training thread failed: {self._error!r}") from self._error
        with self._lock:
            now = time.perf_counter()
            updates = self.agent.updates
            metrics = {key: self._metric_sums[key] / self._metric_counts[key] for key in self._metric_sums}
            self._metric_sums.clear()
            self._metric_counts.clear()
            counts = dict(self._counts)
            rate = (updates - self._updates_reported) / max(now - self._reported_at, 1e-9)
            self._updates_reported, self._reported_at = updates, now
            return {"version": self.version, "updates": updates, "updates_per_s": rate,
                    "store_transitions": len(self.store), "store_episodes": self.store.num_episodes,
                    "demo_transitions": 0 if self.demos is None else len(self.demos), "counts": counts,
                    "metrics": metrics}

    # ---------------------------------------------------------------- weights / state
    def weights_for_sync(self):
        with self._lock:
            return list(self._snapshot)

    def save_checkpoint(self, path: str) -> None:
        with self._lock:
            state: dict[str, Any] = {"agent": self.agent.state_dict(), "store": self.store.state_dict(),
                                     "version": self.version, "counts": dict(self._counts)}
            if self.demos is not None:
                state["demos"] = self.demos.state_dict()
            torch_save_atomic(state, os.path.join(path, _CHECKPOINT))

    def load_checkpoint(self, path: str) -> None:
        state = torch.load(os.path.join(path, _CHECKPOINT), map_location="cpu", weights_only=False)
        with self._lock:
            self.agent.load_state_dict(state["agent"])
            self.store.load_state_dict(state["store"])
            if self.demos is not None and "demos" in state:
                self.demos.load_state_dict(state["demos"])
            self.version = int(state["version"])
            self._counts.update(state["counts"])
            self._observe_stored_since(int(state["store"]["episodes"]))
            self._stored_observed = True
            self._snapshot = self._snap()
            self._updates_reported = self.agent.updates

    def _observe_stored_since(self, first: int) -> None:
        """Fold the episodes the store committed from id ``first`` on (after the checkpoint) into the
        state statistics and the counts, as their ingest did before the restart: their resends are
        recognised as stored and skipped, and those the sender heard of never come again.

        The demonstrations store needs no such pass: scripted demonstrations are recorded at the
        start, after a resume's checkpoint is loaded, and an intervened stretch appended to it after
        the checkpoint is part of an episode folded here (its states counted once, as before)."""
        for episode in _stored_episodes(self.store, first):
            self.agent.observe_states(episode["state"])
            self._counts["episodes"] += 1
            self._counts["steps"] += len(episode["action"])

    def observe_stored(self) -> int:
        """Fold every episode the stores hold into the state statistics (demonstrations first, as a run
        records them before it trains); returns how many were folded. For a learner that starts
        without a checkpoint on stores an earlier run left (one stopped before its first checkpoint,
        ``resume=false`` in its folder, a shared replay path): it samples those episodes from its first
        update on, so the statistics its networks read must have seen them. Without ``normalize_state``
        there are no statistics, and nothing is read. The counts stay this learner's own ingest.

        An intervened stretch in the demonstrations store (every step ``intervened``) is skipped: its
        states are those of the replay store's episode it was cut from, folded once there, as the
        ingest that stored both did."""
        with self._lock:
            if self._stored_observed:
                raise RuntimeError("observe_stored: the stored episodes are in the state statistics already (a "
                                   "checkpoint was loaded, or episodes were stored); folding them again would "
                                   "count them twice")
            self._stored_observed = True
            if self.agent.state_normalizer is None:
                return 0
            folded = 0
            for store in (self.demos, self.store):
                for episode in _stored_episodes(store, 0) if store is not None else ():
                    if store is self.demos and _intervened_stretch(episode):
                        continue
                    self.agent.observe_states(episode["state"])
                    folded += 1
            self._snapshot = self._snap()  # the weights the robots get carry the statistics
            return folded

    def close(self) -> None:
        self.stop()
        with self._lock:
            self.store.close()
            if self.demos is not None:
                self.demos.close()


def _intervened_stretch(episode: dict) -> bool:
    """Whether a demonstrations-store episode is an intervened stretch (scripted demonstrations are
    recorded with no human: none of their steps is intervened)."""
    flags = episode.get("intervened")
    return flags is not None and len(flags) > 0 and bool(np.all(flags != 0))


def _stored_episodes(store: ReplayStore, first: int):
    """The live episodes of ``store`` from id ``first`` on, in commit order (as they were folded in)."""
    for number in sorted(store.segments):
        ids = store.segments[number].episode_ids
        for episode_id in ids[ids >= first].tolist():
            yield store.episode(episode_id)
