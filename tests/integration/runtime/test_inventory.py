"""ClusterInventory: global numbering across nodes, JSON round trip, and rejection of bad input."""
import json

import pytest

from infinirl.runtime.inventory import (
    Accelerator,
    ClusterInventory,
    InventoryError,
    NodeInventory,
    Robot,
)


def test_with_gpus_numbers_devices_across_nodes_in_node_order():
    inv = ClusterInventory.with_gpus(num_nodes=2, gpus_per_node=4)
    assert inv.num_nodes == 2
    assert inv.num_accelerators == 8
    assert inv.accelerator_kind == "cuda"
    assert inv.device_locations[3] == (0, 3)
    assert inv.device_locations[5] == (1, 1)
    assert inv.num_robots == 0


def test_cpu_only_has_no_accelerator_kind_and_numbers_cpu_slots():
    inv = ClusterInventory.cpu_only(num_nodes=2, cpus_per_node=3)
    assert inv.accelerator_kind is None
    assert inv.num_accelerators == 0
    assert inv.num_cpu_slots == 6
    assert inv.cpu_slot_locations[4] == (1, 1)


def test_robots_are_numbered_globally_with_unique_names():
    inv = ClusterInventory.cpu_only(num_nodes=2, robots_per_node=2, robot_kind="franka")
    assert inv.num_robots == 4
    node, robot = inv.robot_locations[3]
    assert node == 1 and robot.name == "franka3" and robot.local_index == 1


def test_accelerators_are_sorted_by_local_index_whatever_the_input_order():
    shuffled = [Accelerator("cuda", 1, 0), Accelerator("cuda", 0, 0)]
    node = NodeInventory(0, "n0", "1.2.3.4", 4, 0, accelerators=shuffled)
    inv = ClusterInventory((node,))
    assert isinstance(node.accelerators, tuple)
    assert inv.device_locations == ((0, 0), (0, 1))


def test_json_round_trip_preserves_everything():
    robot = Robot("arm0", "franka", 0, {"ip": "192.168.1.5"})
    node0 = NodeInventory(0, "abc", "10.0.0.1", 8, 1 << 30, (Accelerator("cuda", 0, 80 << 30),), (robot,))
    node1 = NodeInventory(1, "def", "10.0.0.2", 8, 1 << 30)
    inv = ClusterInventory((node0, node1))
    restored = ClusterInventory.from_dict(json.loads(json.dumps(inv.to_dict())))
    assert restored == inv
    assert restored.nodes[0].robots[0].properties == {"ip": "192.168.1.5"}


def test_from_dict_names_unknown_and_missing_keys():
    data = ClusterInventory.with_gpus(1, 1).to_dict()
    data["nodes"][0]["gpus"] = 3
    with pytest.raises(InventoryError, match=r"unknown key\(s\) \['gpus'\]"):
        ClusterInventory.from_dict(data)
    del data["nodes"][0]["gpus"]
    del data["nodes"][0]["ip"]
    with pytest.raises(InventoryError, match=r"missing key\(s\) \['ip'\]"):
        ClusterInventory.from_dict(data)


def test_rejects_nodes_out_of_order():
    n1 = NodeInventory(1, "b", "ip", 1, 0)
    with pytest.raises(InventoryError, match="position 0 has node_index 1"):
        ClusterInventory((n1,))


def test_rejects_empty_cluster_duplicates_and_mixed_kinds():
    with pytest.raises(InventoryError, match="at least one node"):
        ClusterInventory(())
    with pytest.raises(InventoryError, match=r"duplicate accelerator local_index \[0\]"):
        NodeInventory(0, "a", "ip", 1, 0, (Accelerator("cuda", 0, 0), Accelerator("cuda", 0, 0)))
    mixed = NodeInventory(0, "a", "ip", 1, 0, (Accelerator("cuda", 0, 0), Accelerator("npu", 1, 0)))
    with pytest.raises(InventoryError, match="mixed accelerator kinds"):
        ClusterInventory((mixed,))
    r = Robot("arm", "franka", 0)
    two_nodes_same_robot = tuple(NodeInventory(i, f"n{i}", "ip", 1, 0, robots=(r,)) for i in range(2))
    with pytest.raises(InventoryError, match=r"duplicate robot name\(s\) \['arm'\]"):
        ClusterInventory(two_nodes_same_robot)


def test_rejects_negative_counts():
    with pytest.raises(InventoryError, match="num_cpus must be a non-negative int"):
        NodeInventory(0, "a", "ip", -1, 0)


def test_robot_is_hashable_despite_properties_dict():
    assert len({Robot("a", "k", 0, {"x": 1}), Robot("a", "k", 0, {"x": 1})}) == 1
