"""Robots as cluster resources: the drivers' discovery registered into the runtime's robot plugins,
run on the node by the cluster's discovery task (a process that imported only the runtime), so
`robot:N` puts a rank where the robot is and the rank builds that robot's driver."""

import pytest

from infinirl.realworld.discovery import (
    PLUGIN_MODULE,
    discover_driver_robots,
    parse_discovery_overrides,
    robots_command,
    with_driver_discovery,
)
from infinirl.realworld.robot_worker import RobotSetup, resolve_robot
from infinirl.runtime import ClusterConfig
from infinirl.runtime.hardware import discover_node


def test_discoverer_reports_driver_robots_with_what_builds_them():
    robots = discover_driver_robots({"sim_sawyer": {"instances": 2, "image_size": None}})
    assert [r.name for r in robots] == ["sim_sawyer/0", "sim_sawyer/1"]
    assert robots[1].properties["driver_kind"] == "sim_sawyer"
    assert robots[1].properties["options"] == {"image_size": None, "seed": 1000}
    kind, options = resolve_robot(RobotSetup(kind="sim_so101"), robots[1])
    assert (kind, options) == ("sim_sawyer", {"image_size": None, "seed": 1000})  # the placed robot wins
    assert resolve_robot(RobotSetup(kind="sim_so101", options={"seed": 3}), None) == ("sim_so101", {"seed": 3})
    with pytest.raises(KeyError, match="sim_sawyer"):
        discover_driver_robots({"sim_sawyr": {"instances": 1}})


def test_discover_node_imports_plugin_modules_and_names_the_fix_for_unknown_plugins():
    found = discover_node({"drivers": {"sim_so101": {"instances": 1}}}, plugin_modules=[PLUGIN_MODULE])
    assert [r.name for r in found["robots"]] == ["sim_so101/0"]
    with pytest.raises(KeyError, match="cluster.robot_plugin_modules"):
        discover_node({"no_such_plugin": {}})


def test_with_driver_discovery_adds_the_module_only_when_asked():
    plain = ClusterConfig()
    assert with_driver_discovery(plain) is plain
    asked = with_driver_discovery(ClusterConfig(robot_plugins={"drivers": {}}))
    assert asked.robot_plugin_modules == [PLUGIN_MODULE]
    assert with_driver_discovery(asked).robot_plugin_modules == [PLUGIN_MODULE]


def test_discovery_overrides_parse_and_refuse_bad_items():
    assert parse_discovery_overrides(["sim_sawyer.instances=2", "so101_feetech.ports=[/dev/ttyACM0]"]) == {
        "sim_sawyer": {"instances": 2}, "so101_feetech": {"ports": ["/dev/ttyACM0"]}}
    with pytest.raises(ValueError, match="kind.option=value"):
        parse_discovery_overrides(["instances=2"])
    with pytest.raises(ValueError, match="registered"):
        parse_discovery_overrides(["sim_sawyr.instances=2"])
    assert robots_command(["sim_sawyr.instances=2"]) == 2


def test_cluster_inventory_and_robot_placement_build_the_discovered_robot(ray_cluster, capsys):
    from infinirl.components.sac_learner import SACNetSpec
    from infinirl.realworld.robot_env import RobotEnvSpec
    from infinirl.realworld.robot_worker import RobotActorWorker
    from infinirl.runtime import Cluster, WorkerGroup, place

    config = with_driver_discovery(ClusterConfig(robot_plugins={"drivers": {
        "sim_sawyer": {"instances": 2, "image_size": None, "control_hz": 20.0}}}))
    with Cluster(config) as cluster:  # discovery runs in a task on the node, not in this process
        inventory = cluster.inventory
    assert [robot.name for _, robot in inventory.robot_locations] == ["sim_sawyer/0", "sim_sawyer/1"]
    plan = place(inventory, {"robot": "robot:1"}, components=["robot"])
    group = WorkerGroup.launch(RobotActorWorker, "robot", placement=plan.ranks("robot"),
                               args=(RobotSetup(kind="sim_so101"), RobotEnvSpec(observations=("proprio", "sim_state")),
                                     SACNetSpec(actor_hidden=(8,), critic_hidden=(8,)), 0))
    try:
        described = group.describe().wait()[0]
        assert described["kind"] == "sim_sawyer"  # the placed robot, not the config's kind
        assert described["action_dim"] == 4 and described["obs_dim"] == 43
    finally:
        group.close().wait(timeout=60)
        group.shutdown()

    assert robots_command(["sim_so101.instances=1", "sim_sawyer.instances=1"]) == 0
    printed = capsys.readouterr().out
    assert "robot:0  sim_sawyer/0  kind=sim_sawyer" in printed and "robot:1  sim_so101/0  kind=sim_so101" in printed
