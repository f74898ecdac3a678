"""The run's intervention web page: any laptop or phone on the network watches the robot's cameras
and takes over from the learning policy (docs/intervention_web.md).

:class:`WebInterventionDevice` (registered as ``"web"``) serves one page and a small JSON API from
its own thread and event loop, so the control loop never waits on the network: :meth:`poll` and
:meth:`show` only take a lock. The page shows the latest frames given to :meth:`show` (JPEG, fetched
whenever a newer frame exists), the status (who acts, the policy's proposal, the human's action, the
``info`` given to :meth:`show`), take-over / hand-back and success / failure buttons, and a joystick
(a pad for two axes, sliders for the others) that sets the human's action in ``[-1, 1]``.

The API (every route takes ``?token=`` when the device has a token; a missing or wrong one is a 403):

* ``GET /``: the page; ``GET /api/state``: the status as JSON;
* ``POST /api/takeover`` (optional ``{"action": [...]}``; without one the human starts from a zero
  action): its answer carries ``session``, the id of this take-over. While the control loop runs an
  evaluation or a demonstration (:meth:`WebInterventionDevice.hold_off`) it is a 409 whose ``error``
  says which and that control opens again when the next training episode starts (``held_off`` names
  the kind); a take-over held when one starts goes back to the policy (``released_by``: the kind);
* ``POST /api/action`` ``{"session": ..., "action": [...]}``: ``action_dim`` finite numbers in ``[-1, 1]``;
* ``POST /api/handback`` ``{"session": ...}``: the human's action returns to zero;
* ``POST /api/mark`` ``{"mark": "success" | "failure"}``: delivered once, by the next :meth:`poll`;
* ``GET /api/frame/{camera}``: the camera's latest frame as JPEG.

Only the page holding the latest take-over steers: ``/api/action`` and ``/api/handback`` with any
other session (a page that another page took over from, or one whose control lapsed) are a 409, so
a stale tab never drives the robot or hands back someone else's control. Every POST must be
``Content-Type: application/json`` (415 otherwise) and one whose ``Origin`` is not this server's is a
403: a browser then cannot be made to send a take-over from another site, even without a token
(a cross-site JSON POST needs a CORS preflight, which this server never grants).

Bad input is a 400 whose JSON ``error`` says what to send instead. While the human holds control the
page re-sends its action every ``ACTION_RESEND_S``; if the holder falls silent for
``heartbeat_timeout_s`` (a closed tab, a dropped phone connection) control goes back to the policy
(logged, counted in ``stats.heartbeat_releases``), because a human who cannot see the robot any more
must not keep steering it with a stale action. Only the holding session's actions count as heard.
The status carries ``held_off`` (the kind of the episodes the human stays out of, or null) and
``held_off_message``; the page shows it and disables its take-over button meanwhile.
"""

from __future__ import annotations

import asyncio
import hmac
import io
import ipaddress
import json
import logging
import secrets
import socket
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from importlib import resources
from typing import Any
from urllib.parse import quote, urlsplit

import numpy as np

from infinirl.realworld.intervention.device import (
    EPISODE_MARKS,
    INTERVENTION_DEVICES,
    HumanInput,
    InterventionDevice,
    hold_off_message,
)

__all__ = ["ACTION_RESEND_S", "HeldOff", "StaleSession", "WebControlState", "WebDeviceStats", "WebInterventionDevice",
           "encode_jpeg", "jsonable", "parse_action", "parse_mark"]

logger = logging.getLogger(__name__)

ACTION_RESEND_S = 0.1
"""How often the page re-sends the human's action while it holds control (its heartbeat)."""

_STATIC = "static"


@dataclass(kw_only=True)
class WebDeviceStats:
    """Counters of what happened on the page (read them with ``device.stats``)."""

    takeovers: int = 0
    handbacks: int = 0
    heartbeat_releases: int = 0
    """Control went back to the policy because the holding page fell silent."""
    marks: int = 0
    actions: int = 0
    rejected_requests: int = 0
    """Requests answered 400 (bad input), 403 (missing or wrong token, foreign origin) or 415."""
    stale_requests: int = 0
    """Actions or hand-backs answered 409: sent by a page that no longer holds control. Not an error
    of the page: one already in flight when another page takes over or the heartbeat lapses lands here."""
    refused_takeovers: int = 0
    """Take-overs answered 409 because an evaluation or a demonstration was running."""


def parse_action(value: object, action_dim: int) -> np.ndarray:
    """``value`` as an action: a list of ``action_dim`` finite numbers in ``[-1, 1]``; a one-line
    ``ValueError`` naming what is wrong otherwise."""
    if not isinstance(value, list) or len(value) != action_dim:
        raise ValueError(f"'action' must be a list of {action_dim} numbers in [-1, 1], got {value!r:.80}")
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
        raise ValueError(f"'action' entries must be numbers, got {value!r:.80}")
    action = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(action)) or np.any(np.abs(action) > 1.0):
        raise ValueError(f"'action' entries must be finite and within [-1, 1], got {value!r:.80}")
    return action


def parse_mark(value: object) -> str:
    """``value`` as an episode mark, one of :data:`EPISODE_MARKS`."""
    if value not in EPISODE_MARKS:
        raise ValueError(f"'mark' must be one of {list(EPISODE_MARKS)}, got {value!r:.40}")
    return str(value)


def encode_jpeg(frame: np.ndarray, quality: int) -> bytes:
    """One uint8 ``H x W x 3`` frame as JPEG bytes."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(frame).save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


def jsonable(value: Any) -> Any:
    """``value`` as strict JSON for the page: numpy scalars and arrays become numbers and lists,
    non-finite floats the text ``"nan"`` / ``"inf"`` / ``"-inf"`` (a browser's JSON parser refuses
    ``NaN``), anything else unknown its ``str``."""
    if isinstance(value, np.ndarray | np.generic):
        return jsonable(value.tolist())
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)
    if isinstance(value, bool | int | float | str) or value is None:
        return value
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    return str(value)


def _check_frame(camera: str, frame: np.ndarray) -> np.ndarray:
    frame = np.asarray(frame)
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise ValueError(f"show(): frame {camera!r} must be uint8 H x W x 3, got {frame.dtype} {frame.shape}")
    return np.ascontiguousarray(frame).copy()


class StaleSession(Exception):
    """An action or hand-back from a page that does not hold the present take-over."""


class HeldOff(Exception):
    """A take-over while the control loop runs episodes the human stays out of; ``kind`` says which."""

    def __init__(self, kind: str) -> None:
        super().__init__(hold_off_message(kind))
        self.kind = kind


class WebControlState:
    """What the page set and what the control loop showed, behind one lock (the server thread and
    the control loop share it). ``clock`` is injectable so the heartbeat is testable without sleeping."""

    def __init__(self, *, action_dim: int, heartbeat_timeout_s: float | None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.action_dim = action_dim
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.clock = clock
        self.lock = threading.Lock()
        self.stats = WebDeviceStats()
        self._active = False
        self._action = np.zeros(action_dim)
        self._session: str | None = None  # the take-over in control; None while the policy acts
        self._marks: list[str] = []
        self._last_heard = clock()
        self._released_by: str | None = None  # why control last went back to the policy
        self._held_off: str | None = None  # the kind of the episodes running without the human
        self._policy_action: np.ndarray | None = None
        self._polls = 0
        self._frames: dict[str, np.ndarray] = {}
        self._frame_version = 0
        self._info: dict[str, Any] = {}

    # -- the page's side -------------------------------------------------------------------------
    def take_over(self, action: np.ndarray | None) -> str:
        """A new session holds control (taking it from any page that held it); returns its id.
        Without ``action`` the human starts from zero, never from an earlier take-over's action.
        Refused (:class:`HeldOff`) while held off."""
        with self.lock:
            self._expire()
            if self._held_off is not None:
                self.stats.refused_takeovers += 1
                raise HeldOff(self._held_off)
            self._action = np.zeros(self.action_dim) if action is None else action
            if not self._active:
                self.stats.takeovers += 1
            self._session = secrets.token_urlsafe(12)
            self._active, self._released_by, self._last_heard = True, None, self.clock()
            return self._session

    def hand_back(self, session: str) -> None:
        with self.lock:
            self._check_session(session)
            self.stats.handbacks += 1
            self._release("hand-back")

    def set_action(self, action: np.ndarray, session: str) -> None:
        with self.lock:
            self._check_session(session)
            self._action = action
            self._last_heard = self.clock()
            self.stats.actions += 1

    def _check_session(self, session: str) -> None:
        """Refuse a page other than the holder (caller holds the lock)."""
        self._expire()
        if self._session is None or not hmac.compare_digest(str(session).encode(), self._session.encode()):
            self.stats.stale_requests += 1
            if self._held_off is not None:
                raise StaleSession(f"control went back to the policy: {hold_off_message(self._held_off)}")
            raise StaleSession("this page does not hold control (another page took over, or control went back "
                               "to the policy); take over again to steer")

    def _release(self, why: str) -> None:
        """Control goes back to the policy; the next take-over starts from a zero action (caller
        holds the lock)."""
        self._active, self._released_by, self._session = False, why, None
        self._action = np.zeros(self.action_dim)

    def hold_off(self, kind: str | None) -> None:
        """Episodes of ``kind`` run without the human (None: training again): a take-over in hand
        goes back to the policy now, and new ones are refused until then."""
        with self.lock:
            self._expire()
            self._held_off = kind
            if kind is not None and self._active:
                self._release(kind)
                logger.warning("intervention page: control goes back to the policy: %s", hold_off_message(kind))

    def add_mark(self, mark: str) -> None:
        with self.lock:
            self._marks.append(mark)
            self.stats.marks += 1

    def count_rejected(self) -> None:
        with self.lock:
            self.stats.rejected_requests += 1

    def snapshot(self) -> dict[str, Any]:
        """The status the page shows, as JSON-ready values."""
        with self.lock:
            self._expire()
            return {
                "active": self._active,
                "actor": "human" if self._active else "policy",
                "released_by": self._released_by,
                "held_off": self._held_off,
                "held_off_message": None if self._held_off is None else hold_off_message(self._held_off),
                "action": self._action.tolist(),
                "action_dim": self.action_dim,
                "policy_action": None if self._policy_action is None else jsonable(self._policy_action),
                "polls": self._polls,
                "marks_pending": list(self._marks),
                "cameras": sorted(self._frames),
                "frame_version": self._frame_version,
                "info": self._info,
                "stats": asdict(self.stats),
                "heartbeat_timeout_s": self.heartbeat_timeout_s,
                "action_resend_s": ACTION_RESEND_S,
            }

    def frame(self, camera: str) -> tuple[np.ndarray, int] | None:
        with self.lock:
            frame = self._frames.get(camera)
            return None if frame is None else (frame, self._frame_version)

    # -- the control loop's side -----------------------------------------------------------------
    def poll(self, policy_action: np.ndarray | None) -> HumanInput:
        with self.lock:
            self._expire()
            if policy_action is not None:
                self._policy_action = np.asarray(policy_action, dtype=np.float64).copy()
            self._polls += 1
            marks, self._marks = tuple(self._marks), []
            action = self._action.copy() if self._active else None
            return HumanInput(active=self._active, action=action, marks=marks)

    def show(self, frames: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        with self.lock:
            self._frames.update(frames)
            self._frame_version += 1
            self._info = info

    def _expire(self) -> None:
        """Hand control back if the holding page fell silent (caller holds the lock)."""
        timeout = self.heartbeat_timeout_s
        if self._active and timeout is not None and self.clock() - self._last_heard > timeout:
            self._release("heartbeat")
            self.stats.heartbeat_releases += 1
            logger.warning("intervention page silent for more than %.1f s while holding control: "
                           "control goes back to the policy", timeout)


class _BadRequest(Exception):
    """A request the API refuses with 400 and this message."""


def _same_origin(origin: str | None, host: str | None) -> bool:
    """Whether a request's ``Origin`` header (absent: not a cross-site browser request) names this
    server as the request reached it (``Host``). ``Origin: null`` (a sandboxed frame, a local file)
    is foreign."""
    if origin is None:
        return True
    if not host:
        return False
    parts = urlsplit(origin)
    return parts.scheme in ("http", "https") and parts.netloc.lower() == host.lower()


@INTERVENTION_DEVICES.register("web")
class WebInterventionDevice(InterventionDevice):
    """The intervention web page (see the module docstring).

    ``host`` / ``port``: where to listen (``port=0`` picks a free port; ``0.0.0.0`` for every
    interface, so phones on the network reach it). ``token``: a shared secret every request must
    carry as ``?token=``; ``None`` serves without one (refused off loopback unless
    ``allow_no_token=True``: anyone who reaches the port could move the robot). ``axis_labels``:
    a name per action entry shown beside its control; ``pad_axes``: the two entries the pad moves
    (x: right is +1, y: up is +1). ``timeout_s`` bounds starting and stopping the server.
    """

    def __init__(self, *, action_dim: int, host: str = "127.0.0.1", port: int = 0, token: str | None = None,
                 allow_no_token: bool = False, axis_labels: list[str] | tuple[str, ...] | None = None,
                 pad_axes: tuple[int, int] | list[int] = (0, 1), jpeg_quality: int = 80,
                 heartbeat_timeout_s: float | None = 3.0, timeout_s: float = 10.0) -> None:
        super().__init__(action_dim=action_dim)
        self._check_options(host=host, port=port, token=token, allow_no_token=allow_no_token,
                            jpeg_quality=jpeg_quality, heartbeat_timeout_s=heartbeat_timeout_s, timeout_s=timeout_s)
        self._check_layout(axis_labels=axis_labels, pad_axes=pad_axes)
        self.token = token
        self.axis_labels = tuple(axis_labels) if axis_labels else tuple(f"a{i}" for i in range(action_dim))
        self.pad_axes = tuple(pad_axes) if action_dim >= 2 else ()
        self.jpeg_quality = jpeg_quality
        self.timeout_s = timeout_s
        self.state = WebControlState(action_dim=action_dim, heartbeat_timeout_s=heartbeat_timeout_s)
        self._jpeg_cache: dict[str, tuple[int, bytes]] = {}
        # JPEG encoding runs beside the event loop, so a large frame never delays an API answer.
        self._encoder = ThreadPoolExecutor(max_workers=1, thread_name_prefix="intervention-web-jpeg")
        self._page = resources.files(__package__).joinpath(_STATIC, "index.html").read_bytes()
        self._loop = asyncio.new_event_loop()
        self._runner: Any = None
        self._started = threading.Event()
        self._start_error: BaseException | None = None
        self._closed = False
        self.host, self.port = host, port
        self._thread = threading.Thread(target=self._serve, name="intervention-web", daemon=True)
        self._thread.start()
        if not self._started.wait(timeout_s):
            self._loop.call_soon_threadsafe(self._loop.stop)  # the thread then ends as after a failed start
            raise RuntimeError(f"web intervention device: the server did not start within {timeout_s} s")
        if self._start_error is not None:
            self._thread.join(timeout_s)
            raise RuntimeError(f"web intervention device: cannot serve on {host}:{port}: "
                               f"{self._start_error}") from self._start_error
        logger.info("intervention page: %s", self.url)

    @staticmethod
    def _check_options(*, host: str, port: int, token: str | None, allow_no_token: bool, jpeg_quality: int,
                       heartbeat_timeout_s: float | None, timeout_s: float) -> None:
        if not 0 <= port <= 65535:
            raise ValueError(f"web intervention device: port must be in [0, 65535] (0: a free one), got {port}")
        if token is not None and (not isinstance(token, str) or not token):
            raise ValueError("web intervention device: token must be a non-empty string or None")
        if token is None and not allow_no_token and not _is_loopback(host):
            raise ValueError(f"web intervention device: serving on {host!r} without a token lets anyone who "
                             "reaches the port move the robot; set token=... (or allow_no_token=True)")
        if not 1 <= jpeg_quality <= 95:
            raise ValueError(f"web intervention device: jpeg_quality must be in [1, 95], got {jpeg_quality}")
        if heartbeat_timeout_s is not None and heartbeat_timeout_s <= ACTION_RESEND_S:
            raise ValueError(f"web intervention device: heartbeat_timeout_s must exceed the page's resend "
                             f"period {ACTION_RESEND_S} s (or be None), got {heartbeat_timeout_s}")
        if timeout_s <= 0:
            raise ValueError(f"web intervention device: timeout_s must be > 0, got {timeout_s}")

    def _check_layout(self, *, axis_labels: Any, pad_axes: Any) -> None:
        if axis_labels is not None and len(axis_labels) != self.action_dim:
            raise ValueError(f"web intervention device: axis_labels: one label per action entry "
                             f"({self.action_dim}), got {list(axis_labels)}")
        pad = list(pad_axes)
        if self.action_dim >= 2 and (len(pad) != 2 or pad[0] == pad[1]
                                     or not all(isinstance(a, int) and 0 <= a < self.action_dim for a in pad)):
            raise ValueError(f"web intervention device: pad_axes: two different entries of the action "
                             f"(0..{self.action_dim - 1}), got {pad}")

    # -- the InterventionDevice interface ---------------------------------------------------------
    def poll(self, *, observation: Mapping[str, np.ndarray] | None = None,
             policy_action: np.ndarray | None = None) -> HumanInput:
        if policy_action is not None and np.shape(policy_action) != (self.action_dim,):
            raise ValueError(f"poll(): policy_action must have shape ({self.action_dim},), "
                             f"got {np.shape(policy_action)}")
        return self.state.poll(policy_action)

    def show(self, frames: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> None:
        checked = {str(camera): _check_frame(str(camera), frame) for camera, frame in frames.items()}
        self.state.show(checked, jsonable(dict(info or {})))

    def hold_off(self, kind: str | None) -> None:
        super().hold_off(kind)
        self.state.hold_off(kind)

    @property
    def stats(self) -> WebDeviceStats:
        return self.state.stats

    @property
    def local_address(self) -> tuple[str, int]:
        """Where a process on this machine connects to the page (a tunnel's target)."""
        host = {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(self.host, self.host)
        return host, self.port

    @property
    def url(self) -> str:
        """The page's address, token included: open it in a browser."""
        host = socket.gethostname() if self.host in ("0.0.0.0", "::", "") else self.host
        host = f"[{host}]" if ":" in host else host
        query = f"?token={quote(self.token, safe='')}" if self.token else ""
        return f"http://{host}:{self.port}/{query}"

    def close(self) -> None:
        """Stop the server and its thread; a second call does nothing."""
        if self._closed:
            return
        self._closed = True
        if self._runner is not None and self._loop.is_running():
            future = asyncio.run_coroutine_threadsafe(self._runner.cleanup(), self._loop)
            try:
                future.result(self.timeout_s)
            except TimeoutError:
                future.cancel()
                logger.warning("web intervention device: the server did not stop within %.1f s", self.timeout_s)
        if self._loop.is_running():
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(self.timeout_s)
        if self._thread.is_alive():
            raise RuntimeError(f"web intervention device: its server thread did not end within {self.timeout_s} s")

    # -- the server thread ------------------------------------------------------------------------
    def _serve(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._start())
        except BaseException as error:  # reported by the constructor, which is waiting for it
            self._start_error = error
            self._started.set()
            self._loop.close()
            self._encoder.shutdown(wait=False)
            return
        self._started.set()
        try:
            self._loop.run_forever()
        finally:
            self._loop.run_until_complete(self._loop.shutdown_asyncgens())
            self._loop.close()
            self._encoder.shutdown(wait=True)  # at most the one frame being encoded

    async def _start(self) -> None:
        from aiohttp import web

        app = web.Application(middlewares=[self._guard()], client_max_size=64 * 1024)
        app.router.add_get("/", self._index)
        app.router.add_get("/api/state", self._get_state)
        app.router.add_post("/api/takeover", self._take_over)
        app.router.add_post("/api/handback", self._hand_back)
        app.router.add_post("/api/action", self._set_action)
        app.router.add_post("/api/mark", self._mark)
        app.router.add_get("/api/frame/{camera}", self._frame)
        self._runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port)
        await site.start()
        self.port = int(self._runner.addresses[0][1])

    def _authorised(self, request: Any) -> bool:
        if self.token is None:
            return True
        given = request.query.get("token", "")
        return hmac.compare_digest(given.encode(), self.token.encode())

    def _guard(self) -> Any:
        from aiohttp import web

        @web.middleware
        async def guard(request: Any, handler: Any) -> Any:
            if not self._authorised(request):
                self.state.count_rejected()
                return web.json_response({"error": "missing or wrong token: open the address the run printed, "
                                                   "with its ?token=..."}, status=403)
            if request.method == "POST":
                # Without a token these two checks are what keeps another site's page, open in a
                # browser on this network, from posting a take-over: a form can only send
                # form/text bodies, and a JSON fetch from another origin carries that origin.
                if not _same_origin(request.headers.get("Origin"), request.headers.get("Host")):
                    self.state.count_rejected()
                    return web.json_response({"error": "a request from another site's page is refused: open the "
                                                       "address the run printed"}, status=403)
                if request.content_type != "application/json":
                    self.state.count_rejected()
                    return web.json_response({"error": "POST a JSON body with Content-Type: application/json, "
                                                       f"got {request.content_type!r}"}, status=415)
            try:
                return await handler(request)
            except _BadRequest as error:
                self.state.count_rejected()
                return web.json_response({"error": str(error)}, status=400)
            except StaleSession as error:
                return web.json_response({"error": str(error)}, status=409)
            except HeldOff as error:
                return web.json_response({"error": str(error), "held_off": error.kind}, status=409)

        return guard

    async def _json_body(self, request: Any, *, required: bool) -> dict[str, Any]:
        text = await request.text()
        if not text.strip() and not required:
            return {}
        try:
            body = json.loads(text)
        except json.JSONDecodeError as error:
            raise _BadRequest(f"the body must be a JSON object: {error}") from None
        if not isinstance(body, dict):
            raise _BadRequest(f"the body must be a JSON object, got {type(body).__name__}")
        return body

    def _action_from(self, body: dict[str, Any]) -> np.ndarray:
        if "action" not in body:
            raise _BadRequest(f"the body needs 'action': a list of {self.action_dim} numbers in [-1, 1]")
        try:
            return parse_action(body["action"], self.action_dim)
        except ValueError as error:
            raise _BadRequest(str(error)) from None

    def _session_from(self, body: dict[str, Any]) -> str:
        session = body.get("session")
        if not isinstance(session, str) or not session:
            raise _BadRequest("the body needs 'session': the id /api/takeover answered")
        return session

    def _state_json(self) -> dict[str, Any]:
        return {**self.state.snapshot(), "axis_labels": list(self.axis_labels), "pad_axes": list(self.pad_axes)}

    async def _index(self, request: Any) -> Any:
        from aiohttp import web

        return web.Response(body=self._page, content_type="text/html", headers={"Cache-Control": "no-store"})

    async def _get_state(self, request: Any) -> Any:
        from aiohttp import web

        return web.json_response(self._state_json(), headers={"Cache-Control": "no-store"})

    async def _take_over(self, request: Any) -> Any:
        from aiohttp import web

        body = await self._json_body(request, required=False)
        session = self.state.take_over(self._action_from(body) if "action" in body else None)
        return web.json_response({**self._state_json(), "session": session})

    async def _hand_back(self, request: Any) -> Any:
        from aiohttp import web

        self.state.hand_back(self._session_from(await self._json_body(request, required=True)))
        return web.json_response(self._state_json())

    async def _set_action(self, request: Any) -> Any:
        from aiohttp import web

        body = await self._json_body(request, required=True)
        self.state.set_action(self._action_from(body), self._session_from(body))
        return web.json_response({"ok": True})

    async def _mark(self, request: Any) -> Any:
        from aiohttp import web

        body = await self._json_body(request, required=True)
        try:
            mark = parse_mark(body.get("mark"))
        except ValueError as error:
            raise _BadRequest(str(error)) from None
        self.state.add_mark(mark)
        return web.json_response(self._state_json())

    async def _frame(self, request: Any) -> Any:
        from aiohttp import web

        camera = request.match_info["camera"]
        found = self.state.frame(camera)
        if found is None:
            known = self.state.snapshot()["cameras"]
            return web.json_response({"error": f"no frame from camera {camera!r}; cameras: {known}"}, status=404)
        frame, version = found
        cached = self._jpeg_cache.get(camera)
        if cached is None or cached[0] != version:
            loop = asyncio.get_running_loop()
            data = await loop.run_in_executor(self._encoder, encode_jpeg, frame, self.jpeg_quality)
            cached = self._jpeg_cache[camera] = (version, data)
        return web.Response(body=cached[1], content_type="image/jpeg",
                            headers={"Cache-Control": "no-store", "X-Frame-Version": str(cached[0])})


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
