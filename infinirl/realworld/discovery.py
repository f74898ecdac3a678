"""Robots as cluster resources: the robot drivers' discovery as a runtime robot plugin.

The runtime knows nothing of robot drivers; this module registers the ``drivers`` robot plugin in
the runtime's registry (:func:`~infinirl.runtime.hardware.register_robot_discoverer`). Discovery
runs in a task on every node, in a process that has imported only the runtime, so the cluster
config names this module in ``cluster.robot_plugin_modules`` (:func:`with_driver_discovery` adds it
whenever ``cluster.robot_plugins`` asks for ``drivers``)::

    cluster:
      robot_plugins: {drivers: {so101_feetech: {ports: ["/dev/ttyACM*"]}, sim_sawyer: {instances: 1}}}

Each robot a node reports becomes ``robot:N`` in the inventory, with ``driver_kind`` and ``options``
in its properties; a rank placed on it (``placement.robot: robot:0``) runs on that node and builds
the driver there with ``make_robot(driver_kind, **options)``
(:func:`~infinirl.realworld.robot_worker.resolve_robot`).

``infinirl robots [kind.option=value ...]`` prints what each node sees (:func:`robots_command`).
"""

from __future__ import annotations

import dataclasses
import sys
from typing import Any

from infinirl.realworld.driver import ROBOT_DRIVERS, discover
from infinirl.runtime.hardware import register_robot_discoverer
from infinirl.runtime.inventory import Robot

__all__ = ["DRIVERS_PLUGIN", "PLUGIN_MODULE", "discover_driver_robots", "parse_discovery_overrides",
           "robots_command", "with_driver_discovery"]

DRIVERS_PLUGIN = "drivers"
PLUGIN_MODULE = __name__


@register_robot_discoverer(DRIVERS_PLUGIN)
def discover_driver_robots(options: dict) -> list[Robot]:
    """The robots this node reaches, by driver kind: ``options`` maps a kind to its discovery options
    (``{"sim_sawyer": {"instances": 2}}``), as :func:`~infinirl.realworld.driver.discover` takes them."""
    return [Robot(name=robot.name, kind=robot.kind, local_index=index,
                  properties={"driver_kind": robot.kind, "options": dict(robot.options),
                              "description": robot.description})
            for index, robot in enumerate(discover(options))]


def with_driver_discovery(cluster):
    """``cluster`` (a ClusterConfig) with this module among its plugin modules when its robot
    plugins include ``drivers``; unchanged otherwise."""
    if DRIVERS_PLUGIN not in cluster.robot_plugins or PLUGIN_MODULE in cluster.robot_plugin_modules:
        return cluster
    return dataclasses.replace(cluster, robot_plugin_modules=[*cluster.robot_plugin_modules, PLUGIN_MODULE])


def parse_discovery_overrides(overrides: list[str]) -> dict[str, dict[str, Any]]:
    """``["sim_sawyer.instances=2", "so101_feetech.ports=[/dev/ttyACM0]"]`` -> discovery options by
    kind; values are read as YAML. A malformed item or an unknown kind is a one-line ``ValueError``."""
    import yaml

    config: dict[str, dict[str, Any]] = {}
    for item in overrides:
        key, sep, value = item.partition("=")
        kind, dot, option = key.partition(".")
        if not sep or not dot or not kind or not option:
            raise ValueError(f"{item!r}: write kind.option=value, e.g. sim_sawyer.instances=2")
        if kind not in ROBOT_DRIVERS:
            raise ValueError(f"{item!r}: unknown robot driver kind {kind!r}; registered: "
                             f"{', '.join(ROBOT_DRIVERS.names())}")
        config.setdefault(kind, {})[option] = yaml.safe_load(value)
    return config


def robots_command(overrides: list[str], address: str | None = None, kinds: bool = False) -> int:
    """``infinirl robots``: start (or join) the cluster, run discovery on every node, print the robots."""
    if kinds:
        for name in ROBOT_DRIVERS.names():
            kind = ROBOT_DRIVERS.get(name)
            print(f"{name}: {kind.module}.{kind.driver}")
        return 0
    try:
        config = parse_discovery_overrides(overrides)
    except ValueError as exc:
        print(f"infinirl: robots: {exc}", file=sys.stderr)
        return 2
    from infinirl.runtime import Cluster, ClusterConfig

    cluster = with_driver_discovery(ClusterConfig(address=address, robot_plugins={DRIVERS_PLUGIN: config},
                                                  log_to_driver=False))
    with Cluster(cluster) as running:
        index = 0
        for node in running.inventory.nodes:
            print(f"node {node.node_index} ({node.ip}): {len(node.robots)} robot(s)")
            for robot in node.robots:
                print(f"  robot:{index}  {robot.name}  kind={robot.kind}  options={robot.properties.get('options')}"
                      f"  {robot.properties.get('description', '')}".rstrip())
                index += 1
        if not index:
            print("no robots found; a node offers robots only when told where to look, e.g. "
                  "`infinirl robots so101_feetech.ports=[/dev/ttyACM0]` or `sim_sawyer.instances=1`")
    return 0
