"""The edge's side of the link: ship collected episodes, receive weights, survive outages.

:class:`EdgeClient` runs one background thread that dials the cloud, and, while connected, sends
every episode in its :class:`~infinirl.edge.spool.EpisodeSpool` (oldest first, at most ``window``
awaiting acknowledgement) and applies the weight versions the cloud pushes. When the link drops it
reconnects with exponential backoff (``reconnect_min_s`` doubling to ``reconnect_max_s``, with
jitter) and resends what was not acknowledged; the cloud drops the duplicates by episode id. A
refused certificate is not retried: it is permanent, and :meth:`EdgeClient.check` raises it.

The robot keeps acting meanwhile: :attr:`EdgeClient.weights` is the newest version received, and
:meth:`EdgeClient.offline_s` how long the link has been down, so the control loop can use the last
policy within a staleness bound and hold the robot beyond it (:meth:`policy_usable`). When the link
returns, the client logs how long it was down and how many episodes were spooled meanwhile, and
counts them (``outages``, ``offline_s``, ``episodes_spooled_offline``; :attr:`last_outage`).

While connected it also answers the cloud's tunnel connections (:mod:`infinirl.edge.tunnel`) to
the services in ``tunnel_targets`` (e.g. ``{"page": ("127.0.0.1", 8765)}``, the intervention page),
so the cloud reaches them through the link although the edge opens no port.
"""

from __future__ import annotations

import logging
import random
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from infinirl.edge import protocol
from infinirl.edge.codec import FrameOptions, HeldWeights, WeightBaseError, decode_weights, encode_episode
from infinirl.edge.credentials import TlsFiles, certificate_name, client_context
from infinirl.edge.link import Link, LinkAuthError, LinkError, LinkOptions, dial
from infinirl.edge.spool import EpisodeSpool
from infinirl.edge.tunnel import TunnelEnd, TunnelOptions

__all__ = ["EdgeClient", "EdgeOptions"]

logger = logging.getLogger(__name__)
_POLL_S = 0.1


@dataclass(frozen=True, kw_only=True)
class EdgeOptions:
    """Reconnect backoff (s), episodes in flight, the per-frame send timeout, the link's and the
    tunnel's options."""

    reconnect_min_s: float = 0.2
    reconnect_max_s: float = 5.0
    window: int = 16  # a trainer acknowledges after the learner's commit (a channel hop, an fsync and back)
    send_timeout_s: float = 60.0
    link: LinkOptions = field(default_factory=LinkOptions)
    tunnel: TunnelOptions = field(default_factory=TunnelOptions)


class EdgeClient:
    """See the module docstring. ``name``: this edge (episode ids start with it); ``tunnel_targets``:
    service name -> ``(host, port)`` the cloud may open connections to."""

    def __init__(self, address: tuple[str, int], files: TlsFiles, *, name: str, spool: EpisodeSpool | None = None,
                 frames: FrameOptions | None = None, options: EdgeOptions | None = None,
                 on_weights: Callable[[HeldWeights], None] | None = None,
                 tunnel_targets: Mapping[str, tuple[str, int]] | None = None) -> None:
        self.address, self.name = address, name
        self.tunnel_targets = dict(tunnel_targets or {})
        self.spool = spool if spool is not None else EpisodeSpool(max_bytes=1 << 30)
        self.frames, self.options = frames or FrameOptions(), options or EdgeOptions()
        self.on_weights = on_weights
        self.weights: HeldWeights | None = None
        self.counts: Counter[str] = Counter()
        self.error: BaseException | None = None
        self._context = client_context(files)
        certified = certificate_name(files.cert)
        if certified != name:  # the cloud knows the edge by its certificate and checks its episode ids
            raise ValueError(f"edge name {name!r} differs from the name in its certificate {files.cert} "
                             f"({certified!r}); use --name {certified} or that edge's certificate")
        self._boot = uuid.uuid4().hex[:8]
        self._seq = 0
        self._link: Link | None = None
        self.tunnel: TunnelEnd | None = None  # the present link's, while connected
        self._targets_lock = threading.Lock()
        self._offline_since: float | None = time.monotonic()
        self._outage_from: tuple[float, int] | None = None  # (went down at, episodes submitted then)
        self.last_outage: dict | None = None  # {"offline_s", "episodes_spooled"} of the last outage ended
        self._changed = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"edge-client-{name}", daemon=True)

    # ------------------------------------------------------------------ for the robot's loop
    def start(self) -> EdgeClient:
        self._thread.start()
        return self

    def offer(self, service: str, target: tuple[str, int]) -> None:
        """Let the cloud open tunnel connections to ``service`` at ``target`` from now on (on this link
        and every later one): a service that starts after the client, such as the intervention page
        of a control loop built once the link is up."""
        with self._targets_lock:  # a link starting meanwhile copies the targets before or after this
            self.tunnel_targets[service] = target
            if self.tunnel is not None:
                self.tunnel.targets[service] = target

    def submit(self, episode: Mapping[str, np.ndarray]) -> str:
        """Encode and spool one episode for sending; returns its id. Raises the client's fatal error
        (a refused certificate) and :class:`~infinirl.edge.spool.SpoolFullError`."""
        self.check()
        episode_id = f"{self.name}-{self._boot}-{self._seq}"
        self._seq += 1
        self.spool.put(episode_id, encode_episode(episode, episode_id=episode_id, frames=self.frames))
        self.counts["episodes_submitted"] += 1
        with self._changed:
            self._changed.notify_all()
        return episode_id

    @property
    def connected(self) -> bool:
        link = self._link
        return link is not None and link.alive

    @property
    def link(self) -> Link | None:
        """The present link while connected (other services send and receive on streams of their own)."""
        link = self._link
        return link if link is not None and link.alive else None

    def offline_s(self) -> float:
        """Seconds since the link went down (0 while connected)."""
        link = self._link
        if link is not None:
            return 0.0 if link.alive else time.monotonic() - link.closed_at
        since = self._offline_since
        return 0.0 if since is None else time.monotonic() - since

    def policy_usable(self, max_offline_s: float) -> bool:
        """Whether the held weights may still act: some are held and the link has not been down for
        longer than ``max_offline_s`` (beyond it the robot should hold)."""
        return self.weights is not None and self.offline_s() <= max_offline_s

    def wait_drained(self, timeout: float) -> bool:
        """Wait until the cloud acknowledged every spooled episode; False at ``timeout``."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while len(self.spool):
                self.check()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._changed.wait(min(remaining, _POLL_S))
        return True

    def wait_connected(self, timeout: float) -> bool:
        """Wait for the link to come up; False at ``timeout`` (the cloud may be unreachable for now);
        raises a refused certificate at once."""
        deadline = time.monotonic() + timeout
        while not self.connected:
            self.check()
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return True

    def wait_weights(self, version: int, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self._changed:
            while self.weights is None or self.weights.version < version:
                self.check()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._changed.wait(min(remaining, _POLL_S))
        return True

    def check(self) -> None:
        """Raise what ended the client's thread: a refused certificate, or the failure that stopped it."""
        error = self.error
        if isinstance(error, LinkAuthError):
            raise LinkAuthError(str(error))
        if error is not None:
            raise RuntimeError(f"edge {self.name}: the link's thread failed ({error!r}); episodes stay in "
                               "the spool") from error

    def stats(self) -> dict:
        return {**self.counts, "spooled_episodes": len(self.spool), "spooled_bytes": self.spool.bytes,
                "connected": self.connected, "weights_version": self.weights.version if self.weights else None}

    def close(self, timeout: float = 5.0) -> None:
        self._stop.set()
        link = self._link
        if link is not None:
            link.close("the edge is shutting down")
        self._thread.join(timeout)

    # ------------------------------------------------------------------ the link's thread
    def _hello(self) -> dict:
        held = self.weights
        return {"edge": self.name, "weights_version": held.version if held else None,
                "weights_digest": held.digest if held else None}

    def _run(self) -> None:
        try:
            self._connect_loop()
        except BaseException as exc:  # a dead thread must not pass for an outage: check() raises it
            logger.error("edge %s: the link's thread failed; the client stops", self.name, exc_info=True)
            self.error = exc
        finally:
            with self._changed:  # waiters look at self.error now rather than at their timeout
                self._changed.notify_all()

    def _connect_loop(self) -> None:
        backoff = self.options.reconnect_min_s
        while not self._stop.is_set():
            try:
                link = dial(self.address, self._context, options=self.options.link, hello=self._hello())
            except LinkAuthError as exc:
                logger.error("edge %s: %s", self.name, exc)
                self.error = exc
                return
            except (OSError, LinkError, TimeoutError) as exc:
                self.counts["connect_failures"] += 1
                logger.info("edge %s: cloud unreachable (%s); retrying in %.1f s", self.name, exc, backoff)
                self._stop.wait(backoff * random.uniform(0.8, 1.2))
                backoff = min(backoff * 2, self.options.reconnect_max_s)
                continue
            self.counts["connects"] += 1
            self._back_online()
            self._link, self._offline_since = link, None
            failed = False
            try:
                self._session(link)
            except OSError as exc:  # e.g. the spool's disk: that may pass, so another link after the backoff
                failed = True
                self.counts["session_failures"] += 1
                logger.warning("edge %s: sending failed (%r)", self.name, exc)
                link.close(f"the edge could not send ({exc!r})")
            finally:
                link.close("session ended")
                self._offline_since = link.closed_at or time.monotonic()
                self._outage_from = (self._offline_since, self.counts["episodes_submitted"])
                self._link = None
                self.counts["disconnects"] += 1
                logger.warning("edge %s: link lost (%s); reconnecting", self.name, link.closed_reason)
            if failed:  # a failure that repeats on every link must not make the edge redial at once, in a loop
                self._stop.wait(backoff * random.uniform(0.8, 1.2))
                backoff = min(backoff * 2, self.options.reconnect_max_s)
            else:
                backoff = self.options.reconnect_min_s

    def _back_online(self) -> None:
        """After an outage: count it, and say how long it lasted and what the spool took meanwhile."""
        if self._outage_from is None:
            return
        since, submitted = self._outage_from
        self._outage_from = None
        seconds, spooled = time.monotonic() - since, self.counts["episodes_submitted"] - submitted
        self.counts["outages"] += 1
        self.counts["offline_s"] += seconds
        self.counts["episodes_spooled_offline"] += spooled
        self.last_outage = {"offline_s": seconds, "episodes_spooled": spooled}
        logger.warning("edge %s: link back after %.1f s offline; %d episodes were spooled meanwhile, %d await "
                       "acknowledgement and are sent now", self.name, seconds, spooled, len(self.spool))

    def _session(self, link: Link) -> None:
        in_flight: set[str] = set()
        # always answered, also without targets: unread tunnel messages would fill the stream's inbox
        with self._targets_lock:
            self.tunnel = TunnelEnd(link, targets=self.tunnel_targets, options=self.options.tunnel).start()
        receivers = [threading.Thread(target=self._receiver("acknowledgement receiver", self._receive_acks, link,
                                                            in_flight), daemon=True),
                     threading.Thread(target=self._receiver("weights receiver", self._receive_weights, link),
                                      daemon=True)]
        for thread in receivers:
            thread.start()
        sent_here: set[str] = set()
        try:
            while link.alive and not self._stop.is_set():
                with self._changed:
                    pending = [i for i in self.spool.ids() if i not in sent_here]
                    if not pending or len(in_flight) >= self.options.window:
                        self._changed.wait(_POLL_S)
                        continue
                episode_id = pending[0]
                payload = self.spool.read(episode_id)
                if payload is None:  # acknowledged meanwhile (or its file is gone): no longer in the spool
                    continue
                # In flight before it is on the wire: an acknowledgement arriving before the add would
                # find nothing to discard, and the slot would stay taken for the rest of the link.
                with self._changed:
                    in_flight.add(episode_id)
                    sent_here.add(episode_id)
                try:
                    link.send(protocol.EPISODES, payload, timeout=self.options.send_timeout_s)
                except BaseException:
                    with self._changed:
                        in_flight.discard(episode_id)
                        sent_here.discard(episode_id)
                    raise
                self.counts["episode_sends"] += 1
                self.counts["episode_bytes"] += len(payload)
        except (LinkError, TimeoutError) as exc:
            logger.info("edge %s: sending stopped (%s)", self.name, exc)
        finally:
            link.close("session ended")
            self.tunnel.close("the link closed")
            for thread in receivers:
                thread.join(timeout=5.0)

    def _receiver(self, what: str, receive: Callable[..., None], link: Link, *args) -> Callable[[], None]:
        """``receive(link, *args)`` for a receiver thread: whatever fails in it closes the link with the
        reason, for a receiver that is gone while the link looks alive would stop acknowledgements
        (the window fills and sending stops) or weights for good; the next link starts new ones."""
        def run() -> None:
            try:
                receive(link, *args)
            except Exception as exc:
                reason = f"the edge's {what} failed ({exc!r})"
                logger.error("edge %s: %s; reconnecting", self.name, reason,
                             exc_info=not isinstance(exc, protocol.ProtocolError))
                self.counts["receive_failures"] += 1
                link.close(reason)
        return run

    def _receive_acks(self, link: Link, in_flight: set[str]) -> None:
        while link.alive:
            try:
                ids = protocol.load_episode_ids(link.recv(protocol.EPISODE_ACKS, timeout=1.0))
            except TimeoutError:
                continue
            except LinkError:
                return
            with self._changed:
                for episode_id in ids:
                    in_flight.discard(episode_id)
                    self.counts["episodes_acked"] += int(self.spool.remove(episode_id))
                self._changed.notify_all()

    def _receive_weights(self, link: Link) -> None:
        while link.alive:
            try:
                payload = link.recv(protocol.WEIGHTS, timeout=1.0)
            except TimeoutError:
                continue
            except LinkError:
                return
            try:
                held = decode_weights(payload, self.weights)
            except Exception as exc:  # the payload is the only input (zlib.error is no ValueError): refused,
                # so the cloud sends the next push in full rather than the link closing on every push
                logger.warning("edge %s: %s", self.name, exc if isinstance(exc, WeightBaseError) else repr(exc))
                self.counts["weights_refused"] += 1
                reply = {"refused": str(exc)}
            else:
                if self.on_weights is not None:
                    self.on_weights(held)
                with self._changed:
                    self.weights = held
                    self._changed.notify_all()
                self.counts["weights_received"] += 1
                self.counts["weight_bytes"] += len(payload)
                reply = {"version": held.version, "digest": held.digest}
            try:
                link.send(protocol.WEIGHT_ACKS, protocol.dump(reply), timeout=self.options.send_timeout_s)
            except (LinkError, TimeoutError):
                return
