"""Per-node hardware discovery plugins: accelerators and robots are resources alike.

Discovery runs *on each node* (as a pinned Ray task), because only the node itself can tell which
GPUs and robots it has. Plugins are registered by name so a new accelerator kind or a robot
driver adds one function here or in its own module, never an if/elif in the cluster code.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable

from infinirl.runtime.inventory import Accelerator, Robot

AcceleratorDiscoverer = Callable[[], list[Accelerator]]
RobotDiscoverer = Callable[[dict], list[Robot]]

_ACCELERATOR_DISCOVERERS: dict[str, AcceleratorDiscoverer] = {}
_ROBOT_DISCOVERERS: dict[str, RobotDiscoverer] = {}
ROBOT_DISCOVERER_ENTRY_POINTS = "infinirl.robot_discoverers"
"""Entry-point group of robot discoverers: installed packages register one without an import here."""


def register_accelerator_discoverer(name: str):
    """Decorator: register a function that lists this node's accelerators of one kind."""

    def wrap(fn: AcceleratorDiscoverer) -> AcceleratorDiscoverer:
        _ACCELERATOR_DISCOVERERS[name] = fn
        return fn

    return wrap


def register_robot_discoverer(name: str):
    """Decorator: register a function ``(options) -> [Robot]`` that lists robots on this node."""

    def wrap(fn: RobotDiscoverer) -> RobotDiscoverer:
        _ROBOT_DISCOVERERS[name] = fn
        return fn

    return wrap


def robot_discoverer_names() -> list[str]:
    return sorted(_ROBOT_DISCOVERERS)


@register_accelerator_discoverer("cuda")
def _discover_cuda() -> list[Accelerator]:
    import torch

    if not torch.cuda.is_available():
        return []
    found = []
    for index in range(torch.cuda.device_count()):
        props = torch.cuda.get_device_properties(index)
        found.append(Accelerator(kind="cuda", local_index=index, memory_bytes=int(props.total_memory)))
    return found


@register_robot_discoverer("simulated")
def _discover_simulated_robots(options: dict) -> list[Robot]:
    """Faithful stand-in for robots on machines without any: `options = {"count": 2, "kind": "arm"}`."""
    count = int(options.get("count", 1))
    kind = str(options.get("kind", "simulated_arm"))
    return [
        Robot(name=f"{kind}{i}", kind=kind, local_index=i, properties={"simulated": True})
        for i in range(count)
    ]


def _load_robot_discoverer(name: str) -> None:
    """Import the entry point named ``name`` in :data:`ROBOT_DISCOVERER_ENTRY_POINTS`, if any (its
    module registers the discoverer on import)."""
    from importlib import metadata

    for entry in metadata.entry_points(group=ROBOT_DISCOVERER_ENTRY_POINTS):
        if entry.name == name:
            entry.load()


def discover_node(robot_plugins: dict[str, dict] | None = None, plugin_modules: Iterable[str] = ()) -> dict:
    """Run every accelerator discoverer and the requested robot plugins on *this* node.

    ``plugin_modules`` are imported first: modules that register robot discoverers (this runs in a
    fresh task process on each node, where nothing above the runtime has been imported)."""
    import os
    import socket

    for module in plugin_modules:
        importlib.import_module(module)
    accelerators: list[Accelerator] = []
    for discover in _ACCELERATOR_DISCOVERERS.values():
        accelerators.extend(discover())
    robots: list[Robot] = []
    for name, options in (robot_plugins or {}).items():
        if name not in _ROBOT_DISCOVERERS:
            _load_robot_discoverer(name)
        if name not in _ROBOT_DISCOVERERS:
            raise KeyError(
                f"unknown robot plugin '{name}'; registered: {', '.join(robot_discoverer_names())} (a plugin "
                f"from another package: add its module to cluster.robot_plugin_modules)"
            )
        for robot in _ROBOT_DISCOVERERS[name](options or {}):
            robots.append(
                Robot(
                    name=robot.name,
                    kind=robot.kind,
                    local_index=len(robots),
                    properties=robot.properties,
                )
            )
    return {
        "hostname": socket.gethostname(),
        "pid": os.getpid(),
        "accelerators": accelerators,
        "robots": robots,
    }
