"""The cloud's side of the link: accept edges, store their episodes once, push them weights.

:class:`CloudHub` listens for edges (one accept thread; a refused one is logged and kept in
:attr:`CloudHub.refusals`, one line each). For each connected edge it receives episodes and hands each
new episode id to ``on_episode(edge, episode_id, episode)`` once (an id seen before, from a resend
after an outage, is not delivered again; with ``commit_acks``, see below, one not yet committed is).
When ``on_episode`` raises, the hub closes that edge's link, and the edge resends the episode on its
next one. An episode is acknowledged (the edge then forgets it) only after ``on_episode`` returned,
or with ``commit_acks=True`` only once the owner calls :meth:`CloudHub.commit` with its id: when the
episode is in durable storage (the learner's replay store), so neither a trainer that dies nor a
link that drops in between loses it.
A resend of a committed id is acknowledged again at once. One of a delivered, not yet committed id
is delivered again, since the owner's report of its commit may have been lost (the owner must
recognise ids it stored, as the replay store does by source id, and report them committed again);
its acknowledgement follows the commit, on the edge's link of that moment. Without it, such an id
would stay unacknowledged and hold one of the edge's in-flight slots for good. Episode ids must start
with the edge's certificate name and a dash (:class:`~infinirl.edge.edge_client.EdgeClient` names
them so); an edge sending another id is disconnected, so no edge can shadow another's episodes. Seen ids are kept in
memory; pass ``seen_ids`` (e.g. from the replay store) when the cloud restarts.

An episode that cannot be decoded is skipped and not acknowledged (the edge keeps it and resends it
on its next link), counted (``corrupt_episodes``), logged as an error and kept, one line naming the
error, in :attr:`CloudHub.episode_errors`; the link goes on. Any other failure of an edge's episode
receiver closes that edge's link with a reason naming the error (``receive_failures``, and a line in
``episode_errors``), so it never stops reading while the link looks alive.

:meth:`CloudHub.publish` makes a weight version the newest; every edge gets it as soon as it
acknowledged the previous push (one push in flight per edge, so versions never queue up on a slow
link: an edge that falls behind skips to the newest). The hub keeps, per edge name, the exact
weights the edge acknowledged and encodes the next version as a delta against them when that is
smaller (:mod:`infinirl.edge.codec`); an edge that reconnects holding them continues with deltas.

Each connected edge's link also carries TCP connections from the cloud to services at that edge:
:meth:`CloudHub.tunnel` returns the edge's :class:`~infinirl.edge.tunnel.TunnelEnd`, which a
:class:`~infinirl.edge.tunnel.TunnelListener` on a cloud port uses (:mod:`infinirl.edge.tunnel`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from infinirl.edge import protocol
from infinirl.edge.codec import HeldWeights, decode_episode, encode_weights, weights_header
from infinirl.edge.credentials import TlsFiles, server_context
from infinirl.edge.link import CloudListener, Link, LinkAuthError, LinkError, LinkOptions
from infinirl.edge.tunnel import TunnelEnd, TunnelOptions

__all__ = ["CloudHub", "HubOptions", "wait_for"]

logger = logging.getLogger(__name__)
_POLL_S = 0.1


@dataclass(frozen=True, kw_only=True)
class HubOptions:
    send_timeout_s: float = 60.0
    max_refusals_kept: int = 100
    max_episode_errors_kept: int = 100
    link: LinkOptions = field(default_factory=LinkOptions)
    tunnel: TunnelOptions = field(default_factory=TunnelOptions)


@dataclass(kw_only=True)
class _EdgeState:
    held: HeldWeights | None = None  # what the edge acknowledged
    pending: HeldWeights | None = None  # pushed, not yet acknowledged
    pushes: Counter = field(default_factory=Counter)


class CloudHub:
    """See the module docstring; ``address``: where it listens (after construction)."""

    def __init__(self, listen: tuple[str, int], files: TlsFiles, *,
                 on_episode: Callable[[str, str, dict[str, np.ndarray]], None],
                 seen_ids: Iterable[str] = (), options: HubOptions | None = None, commit_acks: bool = False) -> None:
        self.options = options or HubOptions()
        self.on_episode = on_episode
        self.counts: Counter[str] = Counter()
        self.refusals: deque[str] = deque(maxlen=self.options.max_refusals_kept)
        # one line per episode skipped as undecodable and per episode receiver that failed (its link closed)
        self.episode_errors: deque[str] = deque(maxlen=self.options.max_episode_errors_kept)
        self._listener = CloudListener(*listen, server_context(files), options=self.options.link)
        self.address = self._listener.address
        self.commit_acks = commit_acks
        self._seen: dict[str, str] = dict.fromkeys(seen_ids, "")  # delivered id -> its edge
        self._committed: set[str] = set(self._seen)  # acknowledged at once when resent
        self._lock = threading.Lock()
        self._deliver_lock = threading.Lock()  # held while on_episode runs: the other locks stay free
        self._changed = threading.Condition(self._lock)
        self._latest: tuple[int, dict[str, np.ndarray]] | None = None
        self._edges: dict[str, _EdgeState] = {}
        self._links: dict[int, Link] = {}
        self._tunnels: dict[str, TunnelEnd] = {}  # per edge name, its newest link's
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._accept_thread = threading.Thread(target=self._accept_loop, name="cloud-hub-accept", daemon=True)

    def start(self) -> CloudHub:
        self._accept_thread.start()
        return self

    def publish(self, tensors: Mapping[str, object], version: int) -> None:
        """Make ``version`` the newest weights (float tensors as numpy arrays or torch tensors)."""
        with self._changed:
            self._latest = (version, dict(tensors))
            self._changed.notify_all()

    def commit(self, episode_ids: Iterable[str]) -> int:
        """``commit_acks``: these delivered episodes are stored; acknowledge them to their edges
        (on each edge's present link; an edge offline now is acknowledged when it resends them).
        Returns how many acknowledgements went out."""
        by_edge: dict[str, list[str]] = {}
        with self._deliver_lock:
            for episode_id in episode_ids:
                self._committed.add(episode_id)
                by_edge.setdefault(self._seen.get(episode_id, ""), []).append(episode_id)
        sent = 0
        for edge, ids in by_edge.items():
            self.counts["episodes_committed"] += len(ids)
            link = self.link(edge) if edge else None
            if link is None:
                continue
            try:
                link.send(protocol.EPISODE_ACKS, protocol.dump({"ids": ids}), timeout=self.options.send_timeout_s)
                sent += len(ids)
            except (LinkError, TimeoutError) as exc:  # the edge resends them and is acknowledged then
                logger.info("edge %s: acknowledgement of %d committed episodes not sent (%s)", edge, len(ids), exc)
        return sent

    def connected_edges(self) -> list[str]:
        with self._lock:
            return sorted({link.peer for link in self._links.values() if link.alive})

    def link(self, edge: str) -> Link | None:
        """``edge``'s present link (None while it is not connected): other services (e.g. the
        robot's calls, :mod:`infinirl.edge.robot_calls`) send and receive on streams of their own."""
        with self._lock:
            alive = [link for link in self._links.values() if link.peer == edge and link.alive]
        return alive[-1] if alive else None

    def tunnel(self, edge: str | None = None) -> TunnelEnd | None:
        """The tunnel end of ``edge``'s present link; with ``edge=None`` that of the one connected
        edge. None while that edge is not connected, or (``edge=None``) unless exactly one is."""
        with self._lock:
            alive = {name: end for name, end in self._tunnels.items() if end.alive}
        if edge is not None:
            return alive.get(edge)
        return next(iter(alive.values())) if len(alive) == 1 else None

    def edge_version(self, edge: str) -> int | None:
        with self._lock:
            state = self._edges.get(edge)
            return state.held.version if state is not None and state.held is not None else None

    def stats(self) -> dict:
        with self._lock:
            edges = sorted(self._edges)
        with self._deliver_lock:
            return {**self.counts, "edges": edges, "episodes_seen": len(self._seen),
                    "refusals": len(self.refusals), "episode_errors": len(self.episode_errors)}

    def close(self, timeout: float = 5.0) -> None:
        self._stop.set()
        with self._lock:
            links = list(self._links.values())
        for link in links:
            link.close("the cloud is shutting down")
        self._accept_thread.join(timeout)
        with self._lock:
            threads = list(self._threads)
        for thread in threads:
            thread.join(timeout)
        self._listener.close()

    def __enter__(self) -> CloudHub:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                raw, address = self._listener.accept_connection(timeout=_POLL_S * 2)
            except TimeoutError:
                continue
            except OSError:
                return
            self._spawn(self._admit, raw, address, name="hub-handshake")  # a slow client holds up no one

    def _spawn(self, target, *args, name: str) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True, name=name)
        thread.start()
        with self._lock:
            self._threads = [t for t in self._threads if t.is_alive()] + [thread]

    def _admit(self, raw, address) -> None:
        try:
            link = self._listener.handshake(raw, address)
        except LinkAuthError as exc:
            logger.warning("%s", exc)
            self.refusals.append(str(exc))
            self.counts["refused"] += 1
            return
        except (LinkError, OSError) as exc:
            logger.info("edge connection failed: %s", exc)
            return
        except Exception as exc:  # the handshake closed the socket; the edge retries, and this says why
            logger.error("edge connection at %s:%s failed during its handshake (%r)", *address[:2], exc,
                         exc_info=True)
            return
        if self._stop.is_set():
            link.close("the cloud is shutting down")
            return
        self.counts["connects"] += 1
        tunnel = TunnelEnd(link, options=self.options.tunnel).start()  # drains the stream, accepts no opens
        with self._lock:
            self._links[id(link)] = link
            self._tunnels[link.peer] = tunnel
            state = self._edges.setdefault(link.peer, _EdgeState())
            digest = link.peer_hello.get("weights_digest")
            if state.pending is not None and state.pending.digest == digest:
                state.held = state.pending  # applied, but its acknowledgement was lost with the link
            elif state.held is None or state.held.digest != digest:
                state.held = None  # the edge holds something else (or nothing): next push in full
            state.pending = None
        for target in (self._receive_episodes, self._push_weights):
            self._spawn(target, link, name=f"hub-{link.peer}")

    def _receive_episodes(self, link: Link) -> None:
        try:
            while link.alive and not self._stop.is_set():
                try:
                    payload = link.recv(protocol.EPISODES, timeout=1.0)
                except TimeoutError:
                    continue
                try:
                    episode_id, episode = decode_episode(payload)
                    if not isinstance(episode_id, str):
                        raise ValueError(f"episode id {episode_id!r} is not a string")
                except Exception as exc:  # the payload is the only input: whatever fails, it is corrupt
                    self._skip_corrupt(link, payload, exc)
                    continue
                if not episode_id.startswith(f"{link.peer}-"):  # an edge cannot shadow another's episodes
                    link.close(f"edge {link.peer} sent episode id {episode_id!r} outside its namespace "
                               f"'{link.peer}-...'")
                    self.counts["foreign_ids"] += 1
                    logger.warning("%s", link.closed_reason)
                    return
                self.counts["episode_bytes"] += len(payload)
                if not self._take(link, episode_id, episode):
                    return
        except LinkError as exc:
            logger.info("edge %s: episode stream ended (%s)", link.peer, exc)
        except Exception as exc:  # whatever it is, the link must not outlive its receiver
            # Left open, the link would stop reading every stream once this one's inbox filled (and
            # not count as dead, its inbox being ours to drain): robot calls would wait for answers
            # that cannot come. Closed, the edge reconnects and resends what was not acknowledged.
            reason = (f"the cloud's episode receiver for edge {link.peer} failed ({exc!r}); the edge resends "
                      "what was not acknowledged on its next link")
            self.counts["receive_failures"] += 1
            self.episode_errors.append(reason)
            logger.error("%s", reason, exc_info=not isinstance(exc, TimeoutError))
            link.close(reason)
        finally:
            with self._lock:
                self._links.pop(id(link), None)

    def _skip_corrupt(self, link: Link, payload: bytes, exc: Exception) -> None:
        """An episode that cannot be decoded is skipped, reported and not acknowledged: the edge keeps
        it (and resends it on its next link; until then it takes one of the edge's in-flight slots)
        while the link goes on. Closing the link for it instead would stop every episode, weight push
        and robot call of the edge, again on each reconnect, as the edge resends its oldest first."""
        reason = (f"edge {link.peer}: an episode of {len(payload)} bytes could not be decoded ({exc!r}); skipped "
                  "and not acknowledged, the edge keeps it")
        self.counts["corrupt_episodes"] += 1
        self.episode_errors.append(reason)
        logger.error("%s", reason)

    def _take(self, link: Link, episode_id: str, episode: dict) -> bool:
        """Deliver a new id, acknowledge it when due; False when the delivery failed (link closed)."""
        with self._deliver_lock:  # one delivery at a time, also across an old and a new connection
            fresh = episode_id not in self._seen
            # Delivered, not committed: the owner's commit report may be lost, and then only a new
            # delivery (which the owner recognises) brings the commit that acknowledges it.
            again = not fresh and episode_id not in self._committed
            if fresh or again:
                try:
                    self.on_episode(link.peer, episode_id, episode)
                except Exception as exc:  # not acknowledged: the edge resends it on its next link
                    self.counts["delivery_failures"] += 1
                    link.close(f"the cloud could not take episode {episode_id} ({exc!r}); the edge resends it")
                    logger.warning("%s", link.closed_reason)
                    return False
                self._seen[episode_id] = link.peer
                if not self.commit_acks:
                    self._committed.add(episode_id)
            due = episode_id in self._committed  # else: acknowledged by commit()
        self.counts["episodes" if fresh else "duplicates"] += 1
        self.counts["redelivered"] += int(again)
        if due:
            link.send(protocol.EPISODE_ACKS, protocol.dump({"ids": [episode_id]}), timeout=self.options.send_timeout_s)
        return True

    def _next_push(self, link: Link, state: _EdgeState) -> tuple[int, dict] | None:
        latest = self._latest
        if latest is None or state.pending is not None:
            return None
        if state.held is not None and state.held.version >= latest[0]:
            return None
        return latest

    def _push_weights(self, link: Link) -> None:
        state = self._edges[link.peer]
        acks = threading.Thread(target=self._receive_weight_acks, args=(link, state), daemon=True)
        acks.start()
        try:
            while link.alive and not self._stop.is_set():
                with self._changed:
                    push = self._next_push(link, state)
                    if push is None:
                        self._changed.wait(_POLL_S)
                        continue
                    base = state.held
                payload, result = encode_weights(push[1], push[0], base)
                with self._lock:
                    state.pending = result
                kind = weights_header(payload)["kind"]
                link.send(protocol.WEIGHTS, payload, timeout=self.options.send_timeout_s)
                self.counts[f"weight_pushes_{kind}"] += 1
                self.counts["weight_bytes"] += len(payload)
        except (LinkError, TimeoutError) as exc:
            logger.info("edge %s: weight pushes ended (%s)", link.peer, exc)
        finally:
            acks.join(timeout=5.0)

    def _receive_weight_acks(self, link: Link, state: _EdgeState) -> None:
        try:
            self._follow_weight_acks(link, state)
        except Exception as exc:  # a receiver gone while the link lives would leave a push pending for good
            reason = f"edge {link.peer}: weight acknowledgements stopped ({exc!r})"
            self.counts["receive_failures"] += 1
            logger.error("%s; closing its link", reason, exc_info=not isinstance(exc, protocol.ProtocolError))
            link.close(reason)

    def _follow_weight_acks(self, link: Link, state: _EdgeState) -> None:
        while link.alive and not self._stop.is_set():
            try:
                payload = link.recv(protocol.WEIGHT_ACKS, timeout=1.0)
            except TimeoutError:
                continue
            except LinkError:
                return
            message = protocol.load(payload)
            if not isinstance(message.get("refused", message.get("digest")), str):
                raise protocol.ProtocolError(f"a weights acknowledgement with neither a digest nor a refusal: "
                                             f"{payload[:80]!r}")
            with self._changed:
                if "refused" in message:
                    logger.warning("edge %s refused a weight push: %s", link.peer, message["refused"])
                    self.counts["weight_refusals"] += 1
                    state.held = None
                elif state.pending is not None and message.get("digest") == state.pending.digest:
                    state.held = state.pending
                state.pending = None
                self._changed.notify_all()


def wait_for(predicate: Callable[[], bool], timeout: float) -> bool:
    """Poll ``predicate`` until true or ``timeout`` seconds passed."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)
    return True
