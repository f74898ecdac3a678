"""One robot's control loop, without Ray: the robot, the policy's inference copy, and the loop that never waits.

:class:`RobotControlLoop` drives one robot behind the safety layer through a
:class:`~infinirl.realworld.robot_env.RobotEnv` and acts in one of two ways:

* **asynchronous** (:meth:`RobotControlLoop.start`): a control thread runs episodes back to back
  at the robot's own rate. Before each step it calls ``between_steps`` (where the transport loads
  the newest weights it received: the Ray worker's staged weights, or the edge link's newest
  version), so it acts with the latest policy it has and never waits for one. Each finished episode
  goes to a sender thread that hands it to ``submit`` (a put on the learner's channel, or a submit
  to the edge link's spool): a slow transport delays delivery, not the robot;
* **synchronous** (:meth:`RobotControlLoop.collect`): the call runs whole episodes and returns them.

Every step records the policy version that chose its action (:mod:`~infinirl.realworld.episodes`);
until the first trained weights arrive, actions are uniform in ``[-1, 1]`` (warm-up, version -1).
A safety stop during an episode ends it (kept, not terminated) and the next reset re-arms the robot.
Between episodes (before the first, while a synchronous runner trains, while a full outbox waits for
the transport) the loop holds the robot and keeps the safety layer's heartbeat: a deliberate pause,
which must not stop the robot as a stalled pipeline would.

**Interventions** (an :class:`~infinirl.realworld.intervention.spec.InterventionSpec`): before each
step the loop polls the device with the observation and the policy's proposal; in a training episode,
while the human holds control, the human's action is executed and recorded (``intervened`` = 1). A
mark (success / failure) labels the observations up to it for a success classifier (``labels_dir``)
and, with the reward source ``human``, becomes the reward of the step that led to the marked state
and ends the episode (the env's own success then ends nothing). One more poll after a training
episode's last step collects the marks given for it; in the asynchronous loop a training episode is
held back until the next episode's first poll, whatever that episode's kind, so a mark given while
the robot resets (the person still judging the episode that ended) goes to that episode too.
Evaluation and demonstration episodes are not the human's (:meth:`RobotControlLoop._steps` is the one
place that decides): the device is told (``hold_off``) and refuses take-overs; a human action it
reports anyway is not executed and marks given during them are not used, both counted and logged.

The Ray robot worker (:class:`~infinirl.realworld.robot_worker.RobotActorWorker`) and the edge
node (:mod:`infinirl.edge.robot_node`) both run this class; only the transport differs.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from infinirl.models.sac_encoders import PIXELS_PREFIX
from infinirl.realworld.driver import RobotError, RobotStoppedError, make_robot
from infinirl.realworld.episodes import RANDOM_VERSION, EpisodeRecorder
from infinirl.realworld.intervention.device import hold_off_message
from infinirl.realworld.intervention.human_reward import BackgroundLabelWriter, human_reward
from infinirl.realworld.intervention.metrics import intervention_stats
from infinirl.realworld.intervention.spec import InterventionSpec
from infinirl.realworld.robot_env import RobotEnv, RobotEnvSpec
from infinirl.realworld.safety import SafeRobot, SafetyConfig, ServoFaultError, UnknownPoseError

__all__ = ["VERSION_TENSOR", "EmbodimentActionMask", "PolicyLayout", "RobotControlLoop", "RobotSetup", "connect_robot",
           "embodiment_action_mask", "policy_layouts", "resolve_robot", "unit_box"]

logger = logging.getLogger(__name__)

VERSION_TENSOR = "policy_version"
"""A one-element int64 tensor sent with the weights: the version they are, stamped where they were
snapshotted (so a robot never labels its steps with a version other than the one it acts with)."""
_JOIN_TIMEOUT_S = 30.0
_OUTBOX_EPISODES = 8
"""Finished episodes waiting for the sender. A transport slower than the robot for longer than this
pauses the control loop between episodes rather than growing memory without limit (a camera
episode is tens of MB)."""
_OUTBOX_WAIT_S = 0.2
_CONNECT_TRIES = 3
_IDLE_BEATS_PER_DEADLINE = 4
"""While the loop idles between episodes, the robot's heartbeat is given this many times per
``heartbeat_deadline_s`` (a beat late by a scheduling hiccup must not stop the robot)."""


@dataclass(frozen=True, kw_only=True)
class RobotSetup:
    """Which robot a rank drives when its placement gives it none, and its safety settings."""

    kind: str
    options: Mapping[str, Any] = field(default_factory=dict)
    safety: SafetyConfig = field(default_factory=SafetyConfig)


def resolve_robot(setup: RobotSetup, placed: Any) -> tuple[str, dict]:
    """``(kind, options)`` for ``make_robot``: the placed robot's when discovery found it through a
    driver kind (its properties carry ``driver_kind`` and ``options``), else ``setup``'s."""
    properties = getattr(placed, "properties", None) or {}
    if "driver_kind" in properties:
        return str(properties["driver_kind"]), dict(properties.get("options", {}))
    return setup.kind, dict(setup.options)


@dataclass(frozen=True, kw_only=True)
class PolicyLayout:
    """How one robot's observations and actions sit in the shared policy's vectors.

    Robots of different embodiments feed one policy: its observation is the robot's state, zeros up
    to ``obs_dim - num_embodiments``, then a one-hot of ``embodiment`` (absent with one embodiment);
    its action has ``action_dim`` entries, of which a robot executes its own first ``command_size``
    (the rest are ignored by that robot and stored as drawn; the learner masks them out of what its
    critics see and out of the policy's log-probability: :class:`EmbodimentActionMask`).
    """

    obs_dim: int
    action_dim: int
    embodiment: int = 0
    num_embodiments: int = 1
    command_size: int | None = None
    """The robot's own action entries (None: all ``action_dim``)."""

    def pad_state(self, state: np.ndarray) -> np.ndarray:
        if self.num_embodiments == 1 and len(state) == self.obs_dim:
            return state
        padded = np.zeros(self.obs_dim, np.float32)
        padded[:len(state)] = state
        if self.num_embodiments > 1:
            padded[self.obs_dim - self.num_embodiments + self.embodiment] = 1.0
        return padded


def policy_layouts(described: list[dict]) -> list[PolicyLayout]:
    """One layout per robot rank from their :meth:`RobotActorWorker.describe`: identity when every
    robot has the same shape, else padded to the largest with one embodiment per robot kind."""
    kinds = sorted({d["kind"] for d in described})
    same = len({(d["obs_dim"], d["action_dim"]) for d in described}) == 1
    if same and len(kinds) == 1:
        return [PolicyLayout(obs_dim=d["obs_dim"], action_dim=d["action_dim"]) for d in described]
    obs = max(d["obs_dim"] for d in described) + len(kinds)
    action = max(d["action_dim"] for d in described)
    return [PolicyLayout(obs_dim=obs, action_dim=action, embodiment=kinds.index(d["kind"]), num_embodiments=len(kinds),
                         command_size=d["action_dim"]) for d in described]


class EmbodimentActionMask:
    """``mask(obs) -> [B, action_dim]``: 1 on the action entries the observation's embodiment
    executes, 0 on the padding, read off the kind one-hot at the end of ``obs["state"]`` (see
    :class:`PolicyLayout`). The learner multiplies the actions its critics see by it, so Q does not
    depend on entries no robot of that kind executes, and sums the policy's log-probability over the
    executed entries only (the entropy bonus and the temperature's target count those)."""

    def __init__(self, obs_dim: int, action_dim: int, command_sizes: tuple[int, ...]) -> None:
        self.obs_dim, self.action_dim, self.command_sizes = obs_dim, action_dim, tuple(command_sizes)
        self._table = torch.tensor([[1.0] * size + [0.0] * (action_dim - size) for size in self.command_sizes])

    def __call__(self, obs) -> torch.Tensor:
        state = obs["state"] if isinstance(obs, Mapping) else obs
        one_hot = state[:, self.obs_dim - len(self.command_sizes):]
        return self._table.to(state.device)[one_hot.argmax(-1)]


def embodiment_action_mask(layouts: list[PolicyLayout]) -> EmbodimentActionMask | None:
    """The mask for ``layouts`` (from :func:`policy_layouts`), or None when every robot executes the
    whole action (nothing to mask)."""
    first = layouts[0]
    sizes = {layout.embodiment: layout.command_size or layout.action_dim for layout in layouts}
    if first.num_embodiments == 1 or all(size == first.action_dim for size in sizes.values()):
        return None
    return EmbodimentActionMask(first.obs_dim, first.action_dim, tuple(sizes[e] for e in range(first.num_embodiments)))


def unit_box(action_dim: int) -> SimpleNamespace:
    """The ``[-1, 1]^A`` action space the SAC networks are built for."""
    return SimpleNamespace(low=-np.ones(action_dim, np.float32), high=np.ones(action_dim, np.float32),
                           shape=(action_dim,))


def connect_robot(kind: str, options: dict, safety: SafetyConfig, tries: int = _CONNECT_TRIES) -> SafeRobot:
    """The robot behind the safety layer, connected; a driver whose connect fails (a serial port
    that does not answer yet, a simulator that fails to load) is replaced by a fresh one, up to
    ``tries`` times, before the failure is raised."""
    for attempt in range(1, tries + 1):
        robot = SafeRobot(make_robot(kind, **options), safety)
        try:
            robot.connect()
            return robot
        except RobotError as exc:
            robot.close()
            if attempt == tries:
                raise
            logger.warning("%s: connect failed (%s); trying a fresh driver (%d/%d)", kind, exc, attempt + 1, tries)
    raise AssertionError("unreachable")


class RobotControlLoop:
    """One robot + its policy copy (see the module docstring). ``rank`` seeds the warm-up and
    names the rank in messages; ``net`` builds the actor (a :class:`~infinirl.components.sac_learner.SACNetSpec`)."""

    def __init__(self, setup: RobotSetup, env: RobotEnvSpec, net, *, seed: int, rank: int = 0, placed: Any = None,
                 intervention: InterventionSpec | None = None):
        kind, options = resolve_robot(setup, placed)
        self.robot = connect_robot(kind, options, setup.safety)
        self.rank = rank
        self.env = RobotEnv(self.robot, env, setup.safety)
        self.kind, self.net = kind, net
        self.obs_dim, self.action_dim = self.env.observation_size(), self.env.action_dim
        self.cameras = self.env.camera_shapes()  # as the observations carry them (resized to task.frame_size)
        self.configure(PolicyLayout(obs_dim=self.obs_dim, action_dim=self.action_dim))
        self.policy_version = RANDOM_VERSION
        self.rng = np.random.default_rng([seed, self.rank, 0xAC7])
        self.generator = torch.Generator().manual_seed(int(np.random.SeedSequence([seed, self.rank, 0x7A])
                                                           .generate_state(1)[0]))
        self.counts: Counter[str] = Counter()
        self.recent: list[dict] = []  # finished training episodes since the last stats() call
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sender: threading.Thread | None = None
        self._outbox: queue.Queue = queue.Queue(maxsize=_OUTBOX_EPISODES)
        self._error: BaseException | None = None
        self._sender_error: BaseException | None = None
        self._eval_request: tuple[Callable[[], Any], queue.Queue] | None = None
        self._held: EpisodeRecorder | None = None
        """The asynchronous loop with a human: the last training episode, held back until the next
        episode's first poll (of any kind) brings the marks given while the robot reset."""
        self._idle = threading.Event()
        self._closing = threading.Event()
        self._idle_keeper: threading.Thread | None = None
        self.intervention = intervention
        self.intervention_device = None
        self.labels = None
        if intervention is not None:
            self.intervention_device = intervention.build(self.action_dim)
            self.intervention_device.bind(self.env)
            url = getattr(self.intervention_device, "url", None)
            if url is not None:  # a device people open in a browser: say where (reaches the driver's console)
                print(f"intervention page of robot rank {self.rank}: {url}", flush=True)
            if intervention.labels_dir is not None:
                # written off the control thread: compressing a camera episode would make steps late
                self.labels = BackgroundLabelWriter(intervention.labels_dir, prefix=f"rank{self.rank}")
        self._start_idle_keeper(setup.safety)
        self._pause()  # until the first episode: the learner may take a while to start

    # ---------------------------------------------------------------- idling between episodes
    def _start_idle_keeper(self, safety: SafetyConfig) -> None:
        """Between episodes the loop idles on purpose (the learner updates in synchronous mode, a
        full outbox waits for the transport, the runner has not asked for the next episode yet). The
        safety layer's heartbeat only sees steps and resets, so without beats from here it would
        take the idle for a dead pipeline and stop the robot (torque off: an arm goes limp)."""
        if not safety.heartbeat_deadline_s:
            return
        interval = safety.heartbeat_deadline_s / _IDLE_BEATS_PER_DEADLINE

        def keep() -> None:
            while not self._closing.wait(interval):
                if self._idle.is_set():
                    self.robot.heartbeat()

        self._idle_keeper = threading.Thread(target=keep, name="robot-idle", daemon=True)
        self._idle_keeper.start()

    def _pause(self) -> None:
        """Hold the robot where it is and keep its heartbeat until the next episode's reset."""
        if self._idle.is_set():
            return
        try:
            self.robot.hold()
        except RobotError as exc:  # a robot already stopped by the safety layer stays so; reset re-arms it
            logger.warning("%s: holding the robot between episodes failed (%s)", self.kind, exc)
        self.robot.heartbeat()
        self._idle.set()

    # ---------------------------------------------------------------- what it is
    def describe(self) -> dict:
        spec = self.env.robot_spec
        return {"kind": self.kind, "obs_dim": self.obs_dim, "action_dim": self.action_dim,
                "control_hz": spec.control_hz,
                "cameras": dict(self.cameras)}

    def configure(self, layout: PolicyLayout) -> None:
        """Build the policy copy for ``layout`` (before the first weights arrive)."""
        self.layout = layout
        self.actor = self.net.build_actor(layout.obs_dim, unit_box(layout.action_dim), self.cameras,
                                          layout.num_embodiments).eval()

    # ---------------------------------------------------------------- weights
    def load_weights(self, named_tensors, version: int) -> None:
        own = self.actor.state_dict()
        stamped = version
        with torch.no_grad():
            for name, tensor in named_tensors:
                if name == VERSION_TENSOR:
                    stamped = int(tensor.reshape(-1)[0])
                    continue
                if name not in own:
                    raise KeyError(f"weight {name!r} from the learner has no place in the robot's actor")
                own[name].copy_(tensor)
        self.policy_version = stamped

    # ---------------------------------------------------------------- acting
    @torch.no_grad()
    def act(self, obs: dict, deterministic: bool = False) -> tuple[np.ndarray, int]:
        if self.policy_version == RANDOM_VERSION and not deterministic:
            return self.rng.uniform(-1.0, 1.0, self.layout.action_dim).astype(np.float32), RANDOM_VERSION
        action, _, _ = self.actor.sample(self._policy_input(obs), self.generator, deterministic=deterministic)
        return action[0].numpy(), self.policy_version

    def _policy_input(self, obs: dict) -> dict:
        """A batch of one: the state and the current camera frames (a pixel encoder reads them, the
        state networks read only ``state``)."""
        batch = {"state": torch.from_numpy(np.asarray(obs["state"], np.float32)[None])}
        for key, value in obs.items():
            if key.startswith(PIXELS_PREFIX):
                batch[key] = torch.from_numpy(np.asarray(value, np.uint8)[None])
        return batch

    def _episode(self, policy=None, deterministic: bool = False, between_steps=None,
                 training: bool = True) -> tuple[dict | None, bool]:
        """One episode and whether it succeeded; ``policy(observation) -> action`` replaces the
        actor (demonstrations). Training episodes are counted and reported by :meth:`stats`, and
        are the ones a human may intervene in."""
        recorder = self._steps(policy, deterministic, between_steps, training)
        return self._finish(recorder, training), recorder.success

    def _finish(self, recorder: EpisodeRecorder, training: bool) -> dict | None:
        episode = recorder.finish(interventions=self.intervention_device is not None)
        if episode is not None and training:
            self._count(recorder, episode)
        return episode

    def _steps(self, policy=None, deterministic: bool = False, between_steps=None,
               training: bool = True) -> EpisodeRecorder:
        """Run one episode and return its recorder, not finished. With a held training episode
        (:attr:`_held`), this episode's first poll brings the marks given before any step of it
        (while the robot reset, the person still looking at the episode that ended): they go to the
        held one, which then goes to the sender (also when the loop stops before that poll).

        The human's part is decided here, for every device: only training episodes are theirs. For
        an evaluation (the deterministic policy alone, also when filmed) or a scripted demonstration
        the device is held off (it refuses take-overs and tells its human), and whatever it reports
        is kept out of the episode: no human action is executed, no mark rewards, ends or labels it."""
        human = self.intervention_device
        kind = "training" if training else "evaluation" if policy is None else "demonstration"
        held_off = None if training else kind
        if human is not None and human.held_off != held_off:
            human.hold_off(held_off)  # before the reset, so a page says so while the robot resets
        self._idle.clear()  # the reset re-arms the deadlines; from here the steps give the heartbeat
        obs = self._padded(self.env.reset())
        recorder = EpisodeRecorder(obs)
        if human is not None and training:
            human.reset()
        logged: set[str] = set()  # what this episode already logged as kept out
        while not self._stop.is_set():
            self._raise_if_sender_failed()  # nothing this episode collects could be delivered any more
            if between_steps is not None:
                between_steps()
            action, version, given = self._choose(obs, policy, deterministic, human, kind)
            action, given = self._human_part(action, given, kind, logged)
            if given is not None and self._apply_marks(recorder, given.marks):
                break  # the human's mark ended the episode
            try:
                step = self.env.step(action[:self.action_dim])
            except (RobotStoppedError, UnknownPoseError, ServoFaultError) as exc:
                # The safety layer stopped or held the robot: keep what was collected; the next
                # episode's reset re-reads the pose.
                logger.warning("%s: episode ended by the safety layer (%s)", self.kind, exc)
                self.counts["safety_aborts"] += 1
                break
            obs = self._padded(step.obs)
            self.counts["late_steps"] += int(step.late)
            if step.non_finite:
                self.counts["non_finite_actions"] += 1
            if self._record(recorder, action, obs, step, version, given):
                break
        self._release_held()  # stopped before this episode's first poll
        if human is not None and training and recorder.mark is None and len(recorder):
            self._apply_marks(recorder, human.poll(observation=obs).marks)  # marks given for the last step
        self._pause()
        return recorder

    def _choose(self, obs: dict, policy, deterministic: bool, human, kind: str):
        """``(action, version, the human's input or None)`` for the next step: the policy's (or the
        scripted ``policy``'s) action; the caller puts in the human's where it is theirs to give."""
        if policy is not None:
            action = np.zeros(self.layout.action_dim, np.float32)
            action[:self.action_dim] = policy(self.env.last_observation)
            version = RANDOM_VERSION
        else:
            action, version = self.act(obs, deterministic)
        if human is None:
            return action, version, None
        frames = {key.removeprefix("pixels."): value for key, value in obs.items() if key.startswith("pixels.")}
        if frames:
            human.show(frames, {"episode": kind, "steps": self.env.steps, "policy_version": version})
        return action, version, human.poll(observation=obs, policy_action=action[:self.action_dim])

    def _human_part(self, action: np.ndarray, given, kind: str, logged: set[str]):
        """``(the action to execute, the human input this episode takes or None)`` after a poll: its
        marks go to the held training episode first (given before this episode's first step); only a
        training episode takes the rest, with the human's action where they hold control."""
        if self._held is not None and given is not None and given.marks:
            self._apply_marks(self._held, given.marks)
            given = dataclasses.replace(given, marks=())
        self._release_held()
        if given is None:
            return action, None
        if kind != "training":
            self._keep_out(given, kind, logged)
            return action, None
        if given.active:
            action = np.zeros(self.layout.action_dim, np.float32)
            action[:self.action_dim] = given.action
        return action, given

    def _keep_out(self, given, kind: str, logged: set[str]) -> None:
        """Count and log (once per episode each) what a human gave during an episode of ``kind``,
        which is not theirs: a take-over the device did not refuse itself is not executed, and
        marks are not used (they would judge the policy alone, or a script)."""
        if given.active:
            self.counts["refused_human_steps"] += 1
            if "active" not in logged:
                logged.add("active")
                logger.warning("%s: %s reports a take-over; not executed: %s", self.kind,
                               type(self.intervention_device).__name__, hold_off_message(kind))
        if given.marks:
            self.counts["marks_ignored"] += len(given.marks)
            if "marks" not in logged:
                logged.add("marks")
                logger.warning("%s: mark(s) %s given during a %s episode are not used (marks judge a training "
                               "episode: the running one, or while the robot resets, the one that ended)",
                               self.kind, list(given.marks), kind)

    def _record(self, recorder: EpisodeRecorder, action, obs: dict, step, version: int, given) -> bool:
        """Record one step; returns whether the episode is over."""
        if given is not None and self.intervention.reward == "human":  # only the human's marks reward and end
            recorder.add(action, obs, 0.0, False, version, False, intervened=given.active)
            return self.env.steps >= self.env.spec.max_episode_steps
        recorder.add(action, obs, step.reward, step.terminated, version, step.success,
                     intervened=given is not None and given.active)
        return step.terminated or step.truncated

    def _apply_marks(self, recorder: EpisodeRecorder, marks: tuple[str, ...]) -> bool:
        """Count the marks, label the observations so far, and with the human reward source reward
        the last step and end the episode (returns True then). Marks before the first step have no
        step to reward and are only counted."""
        for mark in marks:
            self.counts[f"marks_{mark}"] += 1
        if not marks or not len(recorder) or recorder.mark is not None:
            return False
        recorder.mark = marks[-1]
        if self.labels is not None:  # the robot's own state, as its env (and a classifier reward) reads it
            observations = dict(recorder.obs)
            if "state" in observations:  # a fleet pads the policy's state and appends the robot's one-hot
                observations["state"] = [np.asarray(row)[:self.obs_dim] for row in observations["state"]]
            self.labels.submit(observations, recorder.mark)
        if self.intervention.reward != "human":
            return False
        outcome = human_reward(marks)
        recorder.relabel_last(reward=outcome.reward, terminated=outcome.terminated, success=outcome.success)
        return True

    def _count(self, recorder: EpisodeRecorder, episode: dict) -> None:
        self.counts["episodes"] += 1
        self.counts["steps"] += len(recorder)
        self.counts["successes"] += int(recorder.success)
        entry = {"return": float(episode["reward"].sum()), "length": len(recorder), "success": recorder.success}
        if self.intervention_device is not None:
            stats = intervention_stats(episode["intervened"])
            self.counts["intervened_steps"] += stats.intervened_steps
            self.counts["takeovers"] += stats.takeovers
            entry.update(intervened_steps=stats.intervened_steps, takeovers=stats.takeovers, mark=recorder.mark)
        with self._lock:
            self.recent.append(entry)

    def _padded(self, obs: dict) -> dict:
        return {**obs, "state": self.layout.pad_state(obs["state"])}

    # ---------------------------------------------------------------- asynchronous
    def start(self, submit: Callable[[dict], None], between_steps: Callable[[], Any] | None = None) -> None:
        """Run episodes back to back on a control thread, calling ``between_steps`` before every step
        (where the newest weights are loaded); each finished one is handed to ``submit`` on a sender
        thread (an exception there stops the loop and is reported by the next :meth:`stats`)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._sender = threading.Thread(target=self._send_loop, args=(submit,), name="robot-sender", daemon=True)
        self._thread = threading.Thread(target=self._control_loop, args=(between_steps,), name="robot-control",
                                        daemon=True)
        self._sender.start()
        self._thread.start()

    def _control_loop(self, between_steps) -> None:
        try:
            while not self._stop.is_set():
                request, self._eval_request = self._eval_request, None
                if request is not None:
                    # A held episode stays held: the evaluation's first poll brings the marks given
                    # for it while the robot reset for the evaluation.
                    request[1].put(request[0]())
                    continue
                recorder = self._steps(between_steps=between_steps)
                if self.intervention_device is not None:
                    self._held = recorder
                else:
                    self._release(recorder)
            self._release_held()
        except BaseException as exc:  # reported by the next stats() / stop() call
            self._idle.clear()  # a failed loop is no deliberate pause: the heartbeat lapses, the robot stops
            if exc is not self._sender_error:
                logger.exception("%s control loop failed", self.kind)
            self._error = self._error or exc
        finally:
            try:
                self._hand_to_sender(None)
            except BaseException:  # the sender already ended: nobody waits for the end marker
                pass

    def _release(self, recorder: EpisodeRecorder) -> None:
        """A finished training episode of the asynchronous loop, counted, to the sender."""
        episode = self._finish(recorder, training=True)
        if episode is not None:
            self._hand_to_sender(episode)

    def _release_held(self) -> None:
        if self._held is not None:
            held, self._held = self._held, None
            self._release(held)

    def _hand_to_sender(self, item: dict | None) -> None:
        """Queue ``item`` for the sender; while the outbox is full, wait for it (the transport is
        behind), and raise the sender's error once it has failed instead of waiting forever."""
        warned = False
        while True:
            self._raise_if_sender_failed()
            try:
                self._outbox.put(item, timeout=_OUTBOX_WAIT_S)
                return
            except queue.Full:
                self._pause()
                if not warned:
                    logger.warning("%s: %d episodes wait for the transport; the robot pauses until one is sent",
                                   self.kind, _OUTBOX_EPISODES)
                    self.counts["outbox_full_waits"] += 1
                    warned = True

    def _raise_if_sender_failed(self) -> None:
        if self._sender_error is not None:
            raise self._sender_error

    def _send_loop(self, submit) -> None:
        while True:
            episode = self._outbox.get()
            if episode is None:
                return
            try:
                submit(episode)
                self.counts["episodes_sent"] += 1
            except BaseException as exc:
                logger.exception("%s: sending an episode failed; the control loop stops", self.kind)
                self._error = self._error or exc
                self._sender_error = exc  # the control loop raises it at its next step or hand-over
                return

    def stop(self) -> dict:
        """Stop the control loop after its present step (the running episode is sent as it is)."""
        self._stop.set()
        for thread in (self._thread, self._sender):
            if thread is not None:
                thread.join(_JOIN_TIMEOUT_S)
        self._thread = self._sender = None
        return self.stats()

    # ---------------------------------------------------------------- synchronous
    def collect(self, num_episodes: int, deterministic: bool = False) -> list[dict]:
        """Run ``num_episodes`` training episodes here and return them (synchronous mode);
        ``deterministic``: the policy acts with ``tanh(mean)`` (HG-DAgger's rollouts)."""
        episodes = [self._episode(deterministic=deterministic)[0] for _ in range(num_episodes)]
        return [e for e in episodes if e is not None]

    def demonstrations(self, num_episodes: int, policy: str, seed: int = 0, noise_std: float = 0.0,
                       options: Mapping[str, Any] | None = None) -> list[dict]:
        """``num_episodes`` episodes of the scripted demo policy ``policy`` (their versions read -1)."""
        from infinirl.realworld.demos import make_demo_policy

        demo = make_demo_policy(policy, self.env, seed=seed, noise_std=noise_std, **dict(options or {}))
        episodes = [self._episode(policy=demo.act, training=False)[0] for _ in range(num_episodes)]
        return [e for e in episodes if e is not None]

    # ---------------------------------------------------------------- evaluation
    def evaluate(self, num_episodes: int) -> dict:
        """``num_episodes`` episodes of the deterministic policy ``tanh(mean)``, not sent to the
        learner; while the control loop runs they take its turn between two training episodes."""
        return self._between_episodes(lambda: self._evaluate(num_episodes))

    def record_video(self, num_episodes: int, path: str, fps: int | None = None) -> dict:
        """``num_episodes`` deterministic episodes filmed by the robot's first camera into the mp4
        ``path`` (frames at every control step; ``fps`` defaults to the control rate, so the video
        plays in real time). Returns ``{"path", "frames", "success_rate"}``, or ``{"skipped": why}``
        when the robot has no camera. Taken between training episodes, like :meth:`evaluate`."""
        cameras = self.env.robot_spec.cameras
        if not cameras:
            return {"skipped": f"{self.kind} has no camera "
                               "(a simulated robot renders one with robot.options.image_size)"}
        return self._between_episodes(lambda: self._film(num_episodes, path, cameras[0].name,
                                                         fps or round(self.env.robot_spec.control_hz)))

    def _film(self, num_episodes: int, path: str, camera: str, fps: int) -> dict:
        from infinirl.envs.video import write_mp4

        frames, successes = [], []

        def grab() -> None:
            frames.append(np.asarray(self.env.last_observation.frames[camera], np.uint8))

        for _ in range(num_episodes):
            episode, success = self._episode(deterministic=True, between_steps=grab, training=False)
            if episode is None:
                break
            grab()  # the episode's last state
            successes.append(float(success))
        if not frames:
            return {"skipped": f"{self.kind}: no episode ran"}
        try:
            written = write_mp4(path, frames, fps=fps)
        except (OSError, RuntimeError, ValueError) as exc:  # a missing encoder must not end the control loop
            return {"skipped": f"{self.kind}: {exc}"}
        return {"path": written, "frames": len(frames),
                "success_rate": float(np.mean(successes)) if successes else float("nan")}

    def _between_episodes(self, work: Callable[[], Any]) -> Any:
        """``work()`` here, or on the control thread between two training episodes while it runs."""
        if self._thread is None:
            return work()
        answer: queue.Queue = queue.Queue()
        self._eval_request = (work, answer)
        while True:
            try:
                return answer.get(timeout=1.0)
            except queue.Empty:
                self._raise_if_failed()

    def _evaluate(self, num_episodes: int) -> dict:
        returns, successes, lengths = [], [], []
        for _ in range(num_episodes):
            episode, success = self._episode(deterministic=True, training=False)
            if episode is None:
                break
            returns.append(float(episode["reward"].sum()))
            lengths.append(len(episode["action"]))
            successes.append(float(success))
        if not returns:
            return {}
        return {"eval/success_rate": float(np.mean(successes)), "eval/return_mean": float(np.mean(returns)),
                "eval/length_mean": float(np.mean(lengths)), "eval/episodes": float(len(returns)),
                "eval/policy_version": float(self.policy_version)}

    # ---------------------------------------------------------------- reporting
    def stats(self) -> dict:
        """Counters and the training episodes finished since the last call."""
        self._raise_if_failed()
        with self._lock:
            recent, self.recent = self.recent, []
        return {"kind": self.kind, "counts": dict(self.counts), "episodes": recent,
                "policy_version": self.policy_version,
                "safety_clips": dict(self.robot.clip_counts), "safety_events": dict(self.robot.event_counts)}

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise RobotError(f"{self.kind} robot control loop failed: {self._error!r}") from self._error

    def close(self) -> None:
        try:
            self.stop()  # raises a failure of the loop, after which the robot must still be let go
        finally:
            try:
                if self.intervention_device is not None:
                    self.intervention_device.close()
                if self.labels is not None:
                    self.labels.close()  # the episodes marked last are written before the robot is let go
            finally:
                self._closing.set()
                if self._idle_keeper is not None:
                    self._idle_keeper.join(_JOIN_TIMEOUT_S)
                self.robot.close()
