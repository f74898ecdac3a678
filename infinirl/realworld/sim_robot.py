"""Simulated robots that behave like real ones: a :class:`RobotDriver` around a physics simulator.

What makes a real robot hard to learn on is not its physics but its clock: it runs at its own rate
in wall-clock time whether or not anyone sends a command, commands arrive late, and a reset takes a
person seconds. :class:`SimulatedRobot` reproduces exactly that around any :class:`SimPlant` (one
simulated embodiment):

* a control thread ticks at ``spec.control_hz`` in wall-clock time; each tick advances the plant by
  one control period of simulated time toward the latest delivered target. A tick that runs late is
  not made up for (the next one starts a period after it ends), so the simulator never runs faster
  than real time, and ``stats.late_ticks`` counts the overruns;
* ``act`` only queues the command; it takes effect at the first tick at least ``latency_s`` after it
  was sent (a newer command delivered by then supersedes it: ``stats.superseded``);
* camera frames are rendered at every tick, so ``observe`` returns at once with the latest snapshot.
  A plant whose frames take longer than a control period to render (software GL and a detailed mesh)
  offers ``capture()``: a copy of the scene that a camera thread renders while the control loop runs
  on, as a real camera streams beside the arm. Frames then lag the state by a render or two, as
  a real camera's do; ``stats.frames`` counts the rendered ones. Each scene copy is stamped with the
  episode it belongs to, so a render still in flight when a reset puts the scene back is dropped
  when it completes (``stats.stale_frames``), and ``reset`` waits for the frame of the scene it
  captured at its end: the first observation of an episode shows that episode's scene, at the
  instant its state was read (nothing ticks in between);
* ``reset`` blocks for ``reset_s`` wall-clock seconds (the scene being put back) and then draws a new
  episode from the seed sequence.

``hold`` freezes the target at the present pose; ``stop`` does the same and refuses commands
(:class:`~infinirl.realworld.driver.RobotStoppedError`) until ``reset``: a simulated arm keeps its
pose when stopped, as an arm with brakes does.

**Lockstep** (``lockstep=True``, for reproducible tests): in real time, what a step observes depends
on where the control thread's ticks fall between the caller's command and its observation (two
clocks that drift against each other and against the scheduler), so two runs from one seed diverge
after a few steps. With lockstep the control thread ticks once per command instead of once per
period: ``act`` returns after the plant has advanced exactly one control period toward it, and
frames are rendered on the control thread at that tick (no camera thread, so they show the present
state). The simulated world then advances one period per command whatever the wall clock does: the
caller still paces its steps (a :class:`~infinirl.realworld.robot_env.RobotEnv` sleeps out each
period), but a late step no longer changes what happens. A real robot's driver cannot do this; the
simulated one does it so that a run's learning metrics are a function of its seeds. Nothing moves
between commands (a hold ticks nothing), and ``latency_s`` must be 0.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from infinirl.realworld.driver import RobotDriver, RobotError, RobotObservation, RobotSpec, RobotStoppedError

__all__ = ["RobotMode", "SimPlant", "SimStats", "SimulatedRobot", "check_lockstep"]

RobotMode = str
"""``"idle"`` (not connected), ``"running"``, ``"holding"``, ``"stopped"``, ``"resetting"``, ``"closed"``."""

_JOIN_TIMEOUT_S = 10.0  # a control tick is one simulator step; far longer means a wedged simulator


class SimPlant(Protocol):
    """One simulated embodiment, driven by one thread only (the robot's control thread)."""

    spec: RobotSpec

    def reset(self, seed: int) -> None:
        """Start a new episode (scene layout drawn from ``seed``), robot at its home pose."""

    def apply(self, target: np.ndarray) -> None:
        """Advance one control period of simulated time, moving toward ``target`` (a command)."""

    def read(self) -> RobotObservation:
        """The present state (no frames, timestamp or tick: the robot adds those)."""

    def render(self, scene: object = None) -> dict[str, np.ndarray]:
        """One uint8 frame per camera of the spec: of the live scene, or of one ``capture()`` returned.
        A plant may also define ``capture() -> scene``; it is then rendered on a camera thread."""

    def close(self) -> None: ...


@dataclass(kw_only=True)
class SimStats:
    """Counters of the control loop, for tests and logs."""

    ticks: int = 0
    late_ticks: int = 0
    commands_sent: int = 0
    commands_applied: int = 0
    superseded: int = 0
    resets: int = 0
    holds: int = 0
    stops: int = 0
    frames: int = 0
    stale_frames: int = 0  # rendered from an episode that a reset ended while they rendered: never shown


class SimulatedRobot(RobotDriver):
    """A :class:`SimPlant` behind the real-robot driver interface (see the module docstring).

    ``plant_factory`` builds the plant (its ``spec`` is read at once, so the driver's spec is known
    before ``connect``). Episode ``k`` (counting from 0) is drawn with seed ``seed + k``. ``lockstep``:
    one tick per command instead of one per period (the module docstring's **Lockstep**).
    """

    def __init__(self, plant_factory: Callable[[], SimPlant], *, latency_s: float = 0.0, reset_s: float = 0.0,
                 seed: int = 0, lockstep: bool = False) -> None:
        if latency_s < 0 or reset_s < 0:
            raise ValueError(f"latency_s and reset_s must be >= 0, got {latency_s} and {reset_s}")
        check_lockstep(lockstep, latency_s)
        self._plant = plant_factory()
        self._spec = self._plant.spec
        self.latency_s = float(latency_s)
        self.reset_s = float(reset_s)
        self.lockstep = bool(lockstep)
        self._tick_requests = self._ticks_done = 0  # lockstep: ticks asked for by act, and ticks run
        self._next_seed = int(seed)
        self.stats = SimStats()
        self._lock = threading.Condition()
        self._pending: deque[tuple[float, np.ndarray]] = deque()  # (deliver at, command), oldest first
        self._target: np.ndarray | None = None
        self._snapshot: RobotObservation | None = None
        self._mode: RobotMode = "idle"
        self._reset_requested = False
        self._stop_after_reset = False
        self._reset_done = threading.Event()
        self._closing = False
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._camera_thread: threading.Thread | None = None
        # Episodes started so far: each scene copy and the frames rendered from it carry the episode
        # it was captured in, so a render that outlives a reset is recognised as the old scene's.
        self._episode = 0
        self._captured: tuple[int, object] | None = None  # (episode, scene copy) the camera renders next
        self._frames: dict[str, np.ndarray] = {}
        self._frames_episode = 0  # the episode self._frames show; 0: none yet
        # Lockstep renders each tick's frames on the control thread: a camera thread's frames lag the
        # state by however many renders the scheduler allows.
        self._capture = getattr(self._plant, "capture", None) if self._spec.cameras and not lockstep else None

    @property
    def spec(self) -> RobotSpec:
        return self._spec

    @property
    def mode(self) -> RobotMode:
        with self._lock:
            return self._mode

    def connect(self) -> None:
        """Start the control loop on a first episode (taking ``reset_s``, as every reset does)."""
        with self._lock:
            if self._mode == "closed":
                raise RobotError(f"{self._spec.kind} was closed; build a new driver")
            if self._thread is not None:
                return
            # The first tick must find a reset requested: before any reset the plant has no state to read.
            self._reset_done.clear()
            self._reset_requested, self._mode = True, "resetting"
            self._thread = threading.Thread(target=self._run, name=f"{self._spec.kind}-control", daemon=True)
            self._thread.start()
            if self._capture is not None:
                self._camera_thread = threading.Thread(target=self._run_camera, name=f"{self._spec.kind}-camera",
                                                       daemon=True)
                self._camera_thread.start()
        self._await_reset()

    def observe(self) -> RobotObservation:
        with self._lock:
            self._raise_if_failed()
            if self._snapshot is None:
                raise RobotError(f"{self._spec.kind} is not connected: call connect() first")
            return self._snapshot

    def act(self, command: np.ndarray) -> None:
        command = self._spec.check_command(command).copy()
        with self._lock:
            self._raise_if_failed()
            if self._mode == "resetting":
                raise RobotError(f"{self._spec.kind} is resetting; act after reset() returns")
            if self._mode == "stopped":
                raise RobotStoppedError(f"{self._spec.kind} is stopped; reset() re-arms it")
            if self._thread is None or self._mode in ("idle", "closed"):
                raise RobotError(f"{self._spec.kind} is not connected: call connect() first")
            self._pending.append((time.monotonic() + self.latency_s, command))
            self.stats.commands_sent += 1
            if self.lockstep:
                self._tick_requests += 1
                self._lock.notify_all()
                self._await_tick(self._tick_requests)

    def _await_tick(self, request: int) -> None:
        """Lockstep: wait (holding the condition's lock) until the control thread has run tick ``request``."""
        deadline = time.monotonic() + _JOIN_TIMEOUT_S
        while self._ticks_done < request and not self._closing and self._error is None:
            left = deadline - time.monotonic()
            if left <= 0:
                raise RobotError(f"{self._spec.kind} did not step its simulation within {_JOIN_TIMEOUT_S} s")
            self._lock.wait(left)
        self._raise_if_failed()
        if self._ticks_done < request:
            raise RobotError(f"{self._spec.kind} was closed while stepping")

    def reset(self) -> RobotObservation:
        with self._lock:
            self._raise_if_failed()
            if self._thread is None:
                raise RobotError(f"{self._spec.kind} is not connected: call connect() first")
            self._reset_done.clear()
            self._reset_requested = True
            self._mode = "resetting"
            self._lock.notify_all()
        return self._await_reset()

    def _await_reset(self) -> RobotObservation:
        # A reset takes reset_s plus one simulator reset; far longer means the control thread died.
        finished = self._reset_done.wait(self.reset_s + _JOIN_TIMEOUT_S)
        with self._lock:
            self._raise_if_failed()
        if not finished:
            raise RobotError(f"{self._spec.kind} did not finish its reset within {self.reset_s + _JOIN_TIMEOUT_S} s")
        return self.observe()

    def hold(self) -> None:
        self._freeze("holding")

    def stop(self) -> None:
        self._freeze("stopped")

    def close(self) -> None:
        with self._lock:
            thread, self._thread = self._thread, None
            self._closing = True
            self._mode = "closed"
            self._lock.notify_all()
        if thread is not None:  # it closes the plant once the camera thread has finished its frame
            thread.join(_JOIN_TIMEOUT_S + self.reset_s)
        else:
            self._plant.close()

    def _freeze(self, mode: RobotMode) -> None:
        """Target := the present pose; pending commands dropped."""
        with self._lock:
            if self._mode in ("idle", "closed"):
                return
            if self._mode == "resetting":  # not following commands anyway; a stop outlasts the reset
                self._stop_after_reset = self._stop_after_reset or mode == "stopped"
                return
            if mode == "stopped":
                self.stats.stops += 1
            else:
                self.stats.holds += 1
            self._pending.clear()
            if self._snapshot is not None:
                self._target = self._snapshot.current_target(self._spec)
            if self._mode != "stopped":  # hold does not re-arm a stopped robot
                self._mode = mode

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise RobotError(f"{self._spec.kind} control loop failed: {self._error!r}") from self._error

    # ---- control thread ------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as error:  # reported by the next call from the user's thread
            with self._lock:
                self._error = error
                self._lock.notify_all()
            self._reset_done.set()
        finally:
            with self._lock:
                self._closing = True  # a failed loop also ends the camera thread
                self._lock.notify_all()
            if self._camera_thread is not None:
                self._camera_thread.join(_JOIN_TIMEOUT_S)
            self._plant.close()

    def _loop(self) -> None:
        if self.lockstep:
            self._lockstep_loop()
            return
        period = self._spec.control_period_s
        next_tick = time.monotonic()
        while True:
            with self._lock:
                while not self._closing and not self._reset_requested and time.monotonic() < next_tick:
                    self._lock.wait(max(0.0, next_tick - time.monotonic()))
                if self._closing:
                    return
                resetting = self._reset_requested
            if resetting:
                self._do_reset()
                next_tick = time.monotonic() + period
                continue
            self._tick()
            next_tick += period
            now = time.monotonic()
            if next_tick < now:  # overran: start the next period now, never catch up
                self.stats.late_ticks += 1
                next_tick = now

    def _lockstep_loop(self) -> None:
        """One tick per command :meth:`act` asked for; resets as in real time."""
        while True:
            with self._lock:
                while not self._closing and not self._reset_requested and self._ticks_done >= self._tick_requests:
                    self._lock.wait()
                if self._closing:
                    return
                resetting = self._reset_requested
            if resetting:
                self._do_reset()
                continue
            self._tick()
            with self._lock:
                self._ticks_done += 1
                self._lock.notify_all()

    def _tick(self) -> None:
        with self._lock:
            command = self._take_delivered(time.monotonic())
            if command is not None and self._mode == "running":
                self._target = command
                self.stats.commands_applied += 1
            elif command is not None and self._mode == "holding":
                self._target = command
                self._mode = "running"
                self.stats.commands_applied += 1
            target = self._target
        if target is not None:
            self._plant.apply(target)
        self._publish()

    def _take_delivered(self, now: float) -> np.ndarray | None:
        """The newest command due by ``now``; older due ones were superseded."""
        delivered = None
        while self._pending and self._pending[0][0] <= now:
            if delivered is not None:
                self.stats.superseded += 1
            delivered = self._pending.popleft()[1]
        return delivered

    def _do_reset(self) -> None:
        with self._lock:
            deadline = time.monotonic() + self.reset_s
            while not self._closing and time.monotonic() < deadline:
                self._lock.wait(deadline - time.monotonic())
            if self._closing:
                return
            seed, self._next_seed = self._next_seed, self._next_seed + 1
        self._plant.reset(seed)
        with self._lock:
            self._episode += 1
            self._pending.clear()
            self._snapshot = None
            if self._capture is not None:
                # The first observation of an episode shows the new scene: any frames that are not of
                # this episode (including a render of the old scene still in flight, which the camera
                # thread drops when it completes) are not waited for. The plant does not tick until
                # this wait is over, so the frame and the state read next show one instant.
                self._frames = {}
                self._captured = (self._episode, self._capture())
                self._lock.notify_all()
                while not self._closing and self._frames_episode != self._episode and self._error is None:
                    self._lock.wait()
            self._raise_if_failed()
        self._publish()
        with self._lock:
            self._ticks_done = self._tick_requests  # lockstep: a new episode starts with no tick owed
            self._target = self._snapshot.current_target(self._spec)
            self._mode = "stopped" if self._stop_after_reset else "running"
            self._stop_after_reset = False
            self._reset_requested = False
            self.stats.resets += 1
        self._reset_done.set()

    def _publish(self) -> None:
        state = self._plant.read()
        if self._capture is None:
            frames = self._plant.render() if self._spec.cameras else {}
            self.stats.frames += bool(frames)
        with self._lock:
            if self._capture is not None:
                if self._captured is None:  # the camera took the last copy: hand it the present scene
                    self._captured = (self._episode, self._capture())
                    self._lock.notify_all()
                frames = self._frames
            self._snapshot = replace(state, frames=frames, timestamp=time.monotonic(), tick=self.stats.ticks)
            self.stats.ticks += 1

    def _run_camera(self) -> None:
        """Renders each scene copy the control loop hands over (the GL context lives on this thread)."""
        try:
            while True:
                with self._lock:
                    while not self._closing and self._captured is None:
                        self._lock.wait()
                    if self._closing:
                        return
                    taken = self._captured
                episode, scene = taken
                frames = self._plant.render(scene)
                with self._lock:
                    self.stats.frames += 1
                    if self._captured is taken:  # else a reset handed over its scene meanwhile: render that next
                        self._captured = None
                    if episode == self._episode:
                        self._frames, self._frames_episode = frames, episode
                    else:  # the scene was put back while this rendered: its frames would show the old episode
                        self.stats.stale_frames += 1
                    self._lock.notify_all()
        except BaseException as error:  # reported by the next call from the user's thread
            with self._lock:
                self._error = error
                self._lock.notify_all()


def check_lockstep(lockstep: bool, latency_s: float) -> None:
    """``lockstep`` with a command latency is refused (the drivers' ``check_options`` call it too)."""
    if lockstep and latency_s:
        raise ValueError(f"lockstep=True applies each command at the next tick, which it runs at once; "
                         f"latency_s={latency_s} has no meaning there: set latency_s=0 or lockstep=false")
