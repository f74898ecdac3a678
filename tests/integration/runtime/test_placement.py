"""Placement: spec parsing, rank layout, env vars, relations/modes and every error message."""
import pickle
import re
from collections import Counter

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from infinirl.runtime.inventory import Accelerator, ClusterInventory, NodeInventory
from infinirl.runtime.placement import ParsedSpec, PlacementError, parse_spec, place

GPUS_2x4 = ClusterInventory.with_gpus(num_nodes=2, gpus_per_node=4)


# ----- parser -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "value, expected",
    [
        ("0-3", ParsedSpec("devices", (0, 1, 2, 3), None, "0-3")),
        ("0,2,5", ParsedSpec("devices", (0, 2, 5), None, "0,2,5")),
        ("4", ParsedSpec("devices", (4,), None, "4")),
        (4, ParsedSpec("devices", (4,), None, "4")),
        ("5,0-1", ParsedSpec("devices", (5, 0, 1), None, "5,0-1")),
        ("0-1:0-7", ParsedSpec("devices", (0, 1), 8, "0-1:0-7")),
        ("0-3:0", ParsedSpec("devices", (0, 1, 2, 3), 1, "0-3:0")),
        ("all", ParsedSpec("all", (), None, "all")),
        ("ALL:0-15", ParsedSpec("all", (), 16, "all:0-15")),
        ("node:2", ParsedSpec("nodes", (2,), None, "node:2")),
        ("node:0-1", ParsedSpec("nodes", (0, 1), None, "node:0-1")),
        ("node:2:0-3", ParsedSpec("nodes", (2,), 4, "node:2:0-3")),
        ("robot:0-1", ParsedSpec("robots", (0, 1), None, "robot:0-1")),
        (" 0 - 3 : 0 - 7 ", ParsedSpec("devices", (0, 1, 2, 3), 8, "0-3:0-7")),
    ],
)
def test_parse_spec_accepts_every_form(value, expected):
    assert parse_spec(value) == expected


@pytest.mark.parametrize(
    "value, why",
    [
        ("", "empty spec"),
        ("x", "'x' is not an index"),
        ("0-", "'0-' is not an index"),
        ("-1", "'-1' is not an index"),
        ("3-1", "descending; write '1-3'"),
        ("0,1,1", "1 listed more than once"),
        ("0-3:0-3:0-3", "too many ':'"),
        ("node:", "missing node list"),
        ("node", "must be followed by node indices"),
        ("robot:0:0", "exactly one process per robot"),
        ("0-3:", "process ranks '' must be"),
        ("gpu:0", "'gpu' is not an index"),
    ],
)
def test_parse_spec_rejects_malformed_with_reason_and_accepted_forms(value, why):
    with pytest.raises(PlacementError) as err:
        parse_spec(value, component="actor")
    message = str(err.value)
    assert message.startswith("placement for 'actor': ")
    assert why in message
    assert "accepted forms: '0-3'" in message and "'robot:0-1'" in message


@pytest.mark.parametrize("ranks", ["4", "1-4", "4-7"])
def test_process_ranks_must_start_at_zero(ranks):
    expected = rf"placement for 'reward': process ranks '{ranks}' in 'node:2:{ranks}' must be a range starting at 0"
    with pytest.raises(PlacementError, match=expected):
        parse_spec(f"node:2:{ranks}", component="reward")


@pytest.mark.parametrize("value", [True, 1.5, None, ["0-3"]])
def test_parse_spec_rejects_non_string_values(value):
    with pytest.raises(PlacementError, match=r"placement for 'actor': spec must be a string or int"):
        parse_spec(value, component="actor")


@given(st.lists(st.integers(0, 40), min_size=1, max_size=8, unique=True))
def test_parse_spec_round_trips_any_index_list(indices):
    assert parse_spec(",".join(map(str, indices))).indices == tuple(indices)


# ----- layout -------------------------------------------------------------------------------------


def test_one_process_per_device_across_two_nodes():
    plan = place(GPUS_2x4, {"rollout": "4-7"})
    ranks = plan.ranks("rollout")
    assert [r.rank for r in ranks] == [0, 1, 2, 3]
    device5 = ranks[1]
    assert (device5.node_index, device5.node_id, device5.node_ip) == (1, "node-1", "10.0.0.2")
    assert device5.global_devices == (5,) and device5.local_devices == (1,)
    assert device5.env_vars == {
        "RANK": "1", "WORLD_SIZE": "4", "LOCAL_RANK": "1", "LOCAL_WORLD_SIZE": "4", "CUDA_VISIBLE_DEVICES": "1",
    }
    assert device5.cpu_slots == () and device5.robot is None


def test_local_rank_counts_only_ranks_on_the_same_node():
    plan = place(GPUS_2x4, {"actor": "2-5"})
    env = [(r.node_index, r.env_vars["LOCAL_RANK"], r.env_vars["LOCAL_WORLD_SIZE"]) for r in plan.ranks("actor")]
    assert env == [(0, "0", "2"), (0, "1", "2"), (1, "0", "2"), (1, "1", "2")]


def test_listed_order_decides_rank_order():
    plan = place(GPUS_2x4, {"actor": "5,0"})
    assert [r.global_devices for r in plan.ranks("actor")] == [(5,), (0,)]


def test_several_processes_per_device_are_contiguous():
    plan = place(GPUS_2x4, {"env": "0-1:0-7"})
    assert [r.global_devices[0] for r in plan.ranks("env")] == [0, 0, 0, 0, 1, 1, 1, 1]
    assert {r.env_vars["CUDA_VISIBLE_DEVICES"] for r in plan.ranks("env")[4:]} == {"1"}
    assert plan.world_size("env") == 8


def test_fewer_processes_than_devices_gives_each_several_devices():
    plan = place(GPUS_2x4, {"rollout": "0-7:0-3"})
    ranks = plan.ranks("rollout")
    assert [r.global_devices for r in ranks] == [(0, 1), (2, 3), (4, 5), (6, 7)]
    assert ranks[2].local_devices == (0, 1) and ranks[2].env_vars["CUDA_VISIBLE_DEVICES"] == "0,1"
    assert ranks[2].node_index == 1


def test_all_places_one_process_per_device():
    plan = place(GPUS_2x4, {"actor": "all"})
    assert plan.devices_of("actor") == tuple(range(8))
    assert place(GPUS_2x4, {"actor": "all:0-15"}).world_size("actor") == 16


def test_int_spec_means_that_device():
    assert place(GPUS_2x4, {"reward": 6}).ranks("reward")[0].global_devices == (6,)


def test_node_placements_have_no_devices_and_hide_gpus():
    plan = place(GPUS_2x4, {"reward": "node:1", "env": "node:0-1", "tools": "node:1:0-3", "spread": "node:0-1:0-3"})
    reward = plan.ranks("reward")[0]
    assert reward.node_index == 1 and reward.global_devices == () and reward.cpu_slots == ()
    assert reward.env_vars["CUDA_VISIBLE_DEVICES"] == ""
    assert [r.node_index for r in plan.ranks("env")] == [0, 1]
    assert [r.node_index for r in plan.ranks("tools")] == [1, 1, 1, 1]
    assert [r.env_vars["LOCAL_RANK"] for r in plan.ranks("tools")] == ["0", "1", "2", "3"]
    assert [r.node_index for r in plan.ranks("spread")] == [0, 0, 1, 1]
    assert plan.devices_of("reward") == ()


def test_cpu_only_cluster_places_on_cpu_slots_without_visible_devices():
    inv = ClusterInventory.cpu_only(num_nodes=2, cpus_per_node=2)
    plan = place(inv, {"actor": "0-1", "rollout": "2-3:0-3"})
    actor = plan.ranks("actor")
    assert [(r.node_index, r.cpu_slots) for r in actor] == [(0, (0,)), (0, (1,))]
    assert all(r.global_devices == () and r.local_devices == () for r in actor)
    assert all("CUDA_VISIBLE_DEVICES" not in r.env_vars for r in plan.ranks("actor") + plan.ranks("rollout"))
    assert [(r.node_index, r.cpu_slots) for r in plan.ranks("rollout")] == [(1, (2,)), (1, (2,)), (1, (3,)), (1, (3,))]
    assert plan.devices_of("rollout") == (2, 3)
    assert plan.relation("actor", "rollout") == "disaggregated"
    assert place(inv, {"actor": "all"}).world_size("actor") == 4


def test_cpu_only_slot_beyond_cluster_explains_slots():
    with pytest.raises(PlacementError) as err:
        place(ClusterInventory.cpu_only(), {"actor": "0-2"})
    assert str(err.value) == (
        "placement for 'actor': CPU slot 2 does not exist (cluster has 2 CPU slots: 0-1 on 1 node; "
        "on a CPU-only cluster device indices are CPU slots)"
    )


def test_robots_attach_to_ranks_on_their_nodes():
    inv = ClusterInventory.with_gpus(num_nodes=2, gpus_per_node=1, robots_per_node=1, robot_kind="franka")
    plan = place(inv, {"robot_env": "robot:0-1", "actor": "0-1"})
    ranks = plan.ranks("robot_env")
    assert [(r.node_index, r.robot.name) for r in ranks] == [(0, "franka0"), (1, "franka1")]
    assert all(r.global_devices == () and r.env_vars["CUDA_VISIBLE_DEVICES"] == "" for r in ranks)
    assert plan.robots_of("robot_env") == (inv.nodes[0].robots[0], inv.nodes[1].robots[0])
    assert plan.relation("robot_env", "actor") == "disaggregated"


def test_robots_on_a_cpu_only_cluster_get_no_visible_devices_variable():
    inv = ClusterInventory.cpu_only(robots_per_node=2)
    rank = place(inv, {"env": "robot:1"}).ranks("env")[0]
    assert rank.robot.name == "arm1" and "CUDA_VISIBLE_DEVICES" not in rank.env_vars


def test_visible_devices_variable_follows_accelerator_kind():
    inv = ClusterInventory.with_gpus(1, 2, kind="npu")
    assert place(inv, {"actor": "1"}).ranks("actor")[0].env_vars["ASCEND_RT_VISIBLE_DEVICES"] == "1"
    inv = ClusterInventory.with_gpus(1, 2, kind="tpu")
    assert place(inv, {"actor": "1"}).ranks("actor")[0].env_vars["TPU_VISIBLE_DEVICES"] == "1"


def test_local_device_index_comes_from_the_inventory_not_the_position():
    # A node whose runtime exposes only cuda:2 and cuda:3 (e.g. the rest are taken by another job).
    node = NodeInventory(0, "n0", "ip", 8, 0, (Accelerator("cuda", 2, 0), Accelerator("cuda", 3, 0)))
    rank = place(ClusterInventory((node,)), {"actor": "1"}).ranks("actor")[0]
    assert rank.global_devices == (1,) and rank.local_devices == (3,)
    assert rank.env_vars["CUDA_VISIBLE_DEVICES"] == "3"


def test_comma_key_places_several_components_identically():
    plan = place(GPUS_2x4, {"actor, rollout": "0-3"}, components=["actor", "rollout"])
    assert list(plan.components) == ["actor", "rollout"]
    assert plan.devices_of("actor") == plan.devices_of("rollout") == (0, 1, 2, 3)
    assert plan.ranks("rollout")[0].component == "rollout"


# ----- relations and modes ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "spec, mode",
    [
        ({"actor": "0-3"}, "collocated"),
        ({"actor": "0-3", "rollout": "0-3", "reward": "2"}, "collocated"),
        ({"actor": "0-3", "rollout": "4-7"}, "disaggregated"),
        ({"actor": "0-7", "rollout": "0-3", "env": "4-7"}, "hybrid"),
        ({"actor": "0-3", "rollout": "0-3", "reward": "node:0"}, "collocated"),
        ({"actor": "0-3", "reward": "node:0", "env": "node:1"}, "collocated"),
        ({"actor": "0-1", "rollout": "1-2", "env": "2-3"}, "hybrid"),  # collocation is not transitive
    ],
)
def test_mode(spec, mode):
    assert place(GPUS_2x4, spec).mode == mode


def test_node_placed_components_are_disaggregated_from_everything_but_themselves():
    plan = place(GPUS_2x4, {"actor": "0-3", "reward": "node:0", "verifier": "node:0"})
    assert plan.relation("actor", "reward") == "disaggregated"
    assert plan.relation("reward", "verifier") == "disaggregated"
    assert plan.relation("reward", "reward") == "collocated"


def test_partial_overlap_is_collocated_and_components_on_device_lists_sharers():
    plan = place(GPUS_2x4, {"actor": "0-3", "rollout": "3-6", "reward": "node:0"})
    assert plan.relation("actor", "rollout") == plan.relation("rollout", "actor") == "collocated"
    assert plan.components_on_device(3) == ("actor", "rollout")
    assert plan.components_on_device(7) == ()


def test_sharing_a_robot_is_collocated_and_robot_components_count_in_the_mode():
    inv = ClusterInventory.with_gpus(1, 4, robots_per_node=2)
    plan = place(inv, {"actor": "0-3", "rollout": "0-3", "env": "robot:0-1", "teleop": "robot:1"})
    assert plan.relation("env", "teleop") == "collocated"
    assert plan.relation("env", "actor") == "disaggregated"
    assert plan.mode == "hybrid"  # actor~rollout take turns, env streams beside them


def test_plan_survives_pickling_as_ray_would_send_it():
    plan = place(ClusterInventory.with_gpus(2, 2, robots_per_node=1), {"actor": "0-3", "env": "robot:0-1"})
    assert pickle.loads(pickle.dumps(plan)) == plan


def test_describe_lists_every_rank():
    plan = place(GPUS_2x4, {"actor": "0-1", "reward": "node:1"})
    lines = plan.describe().splitlines()
    assert lines[0] == "placement (collocated) on 2 nodes, 8 cuda devices"
    assert lines[1].split() == ["component", "rank", "node", "ip", "devices", "local", "robot"]
    assert lines[3].split() == ["actor", "1/2", "0", "10.0.0.1", "1", "1", "-"]
    assert lines[4].split() == ["reward", "0/1", "1", "10.0.0.2", "-", "-", "-"]
    cpu = place(ClusterInventory.cpu_only(), {"actor": "0-1"}).describe()
    assert "cpu slots" in cpu and "CPU-only" in cpu


# ----- errors -------------------------------------------------------------------------------------


def _error(spec, inventory=GPUS_2x4, **kwargs) -> str:
    with pytest.raises(PlacementError) as err:
        place(inventory, spec, **kwargs)
    return str(err.value)


def test_error_device_does_not_exist():
    assert _error({"rollout": "4-9"}) == (
        "placement for 'rollout': device 8 does not exist (cluster has 8 cuda devices: 0-7)"
    )
    assert _error({"rollout": "9"}) == (
        "placement for 'rollout': device 9 does not exist (cluster has 8 cuda devices: 0-7)"
    )


def test_error_unknown_component_lists_known_ones_and_suggests():
    message = _error({"actr": "0-3"}, components=["actor", "rollout", "reward"])
    assert message == (
        "placement names unknown component 'actr'; known components: actor, rollout, reward (did you mean 'actor'?)"
    )
    assert "known components: actor, reward, rollout" in _error({"x": "0"}, components={"rollout", "actor", "reward"})


def test_known_component_missing_from_spec_is_allowed():
    assert list(place(GPUS_2x4, {"actor": "0"}, components=["actor", "rollout"]).components) == ["actor"]


def test_error_empty_spec_and_bad_arguments():
    assert "placement spec is empty" in _error({})
    assert "must be a mapping" in _error("0-3")
    assert "max_procs_per_device must be a positive int, got 0" in _error({"a": "0"}, max_procs_per_device=0)
    assert "keys must be component names" in _error({3: "0"})
    assert "key 'actor,' has an empty component name" in _error({"actor,": "0"})


def test_error_component_given_twice():
    assert _error({"actor,rollout": "0-3", "rollout": "4-7"}) == (
        "placement for 'rollout' is given twice (keys 'actor,rollout' and 'rollout'); give each component one entry"
    )


def test_error_malformed_names_component_and_forms():
    message = _error({"reward": "gpu0"})
    assert message.startswith("placement for 'reward': cannot parse 'gpu0'")
    assert "accepted forms:" in message


def test_error_robot_beyond_cluster():
    inv = ClusterInventory.with_gpus(1, 2, robots_per_node=2)
    assert _error({"env": "robot:1-2"}, inv) == (
        "placement for 'env': robot 2 does not exist (cluster has 2 robots: 0-1)"
    )
    assert _error({"env": "robot:0"}) == "placement for 'env': robot 0 does not exist (cluster has no robots)"


def test_error_node_beyond_cluster():
    assert _error({"reward": "node:2"}) == (
        "placement for 'reward': node 2 does not exist (cluster has 2 nodes: 0-1)"
    )


def test_error_too_many_processes_per_device():
    message = _error({"env": "0:0-8"})
    assert message.startswith("placement for 'env': 9 processes on 1 device (0) puts 9 on each device")
    assert "max_procs_per_device=8" in message
    assert place(GPUS_2x4, {"env": "0:0-8"}, max_procs_per_device=9).world_size("env") == 9
    assert "max_procs_per_device=2" in _error({"env": "0-1:0-5"}, max_procs_per_device=2)


def test_error_processes_not_divisible_over_devices():
    message = _error({"env": "0-1:0-2"})
    assert message.startswith("placement for 'env': 3 processes cannot be spread evenly over 2 devices (0-1)")
    assert "use a multiple of 2 processes" in message
    assert _error({"rollout": "0-2:0-1"}) == (
        "placement for 'rollout': 2 processes cannot share 3 devices (0-2) evenly; "
        "use a divisor or a multiple of 3 processes"
    )


def test_error_process_spanning_nodes():
    assert _error({"rollout": "3-4:0"}) == (
        "placement for 'rollout': rank 0 would get devices 3-4 on nodes [0, 1]; "
        "a process's devices must be on one node, so use more processes"
    )


def test_error_fewer_processes_than_nodes():
    assert _error({"reward": "node:0-1:0"}) == (
        "placement for 'reward': 1 process cannot cover 2 nodes (0-1); "
        "a process runs on one node, so use at least one per node"
    )
    assert _error({"reward": "node:0-1:0-2"}) == (
        "placement for 'reward': 3 processes cannot be spread evenly over 2 nodes (0-1); use a multiple of 2 processes"
    )


def test_error_query_for_unknown_component_or_device():
    plan = place(GPUS_2x4, {"actor": "0"})
    with pytest.raises(PlacementError, match="plan has no component 'rollout'; components: actor"):
        plan.devices_of("rollout")
    with pytest.raises(PlacementError, match=re.escape("device 8 does not exist (cluster has 8 cuda devices: 0-7)")):
        plan.components_on_device(8)


# ----- properties ---------------------------------------------------------------------------------


@st.composite
def clusters_and_specs(draw):
    """A random cluster plus up to 3 valid device specs: index lists and k processes per device."""
    if draw(st.booleans()):
        inventory = ClusterInventory.with_gpus(draw(st.integers(1, 3)), draw(st.integers(1, 4)))
    else:
        inventory = ClusterInventory.cpu_only(draw(st.integers(1, 3)), draw(st.integers(1, 4)))
    pool = inventory.num_accelerators or inventory.num_cpu_slots
    max_procs = draw(st.integers(1, 4))
    spec, expected = {}, {}
    for i in range(draw(st.integers(1, 3))):
        devices = draw(st.lists(st.integers(0, pool - 1), min_size=1, max_size=pool, unique=True))
        per_device = draw(st.integers(1, max_procs))
        text = ",".join(map(str, devices))
        if per_device > 1 or draw(st.booleans()):
            text += f":0-{per_device * len(devices) - 1}"
        spec[f"c{i}"] = text
        expected[f"c{i}"] = (devices, per_device)
    return inventory, spec, expected, max_procs


@settings(max_examples=150, deadline=None)
@given(clusters_and_specs())
def test_random_valid_specs_satisfy_placement_invariants(case):
    inventory, spec, expected, max_procs = case
    plan = place(inventory, spec, components=list(spec), max_procs_per_device=max_procs)
    on_cpu = inventory.accelerator_kind is None
    locations = inventory.cpu_slot_locations if on_cpu else inventory.device_locations
    for name, ranks in plan.components.items():
        devices, per_device = expected[name]
        world = len(devices) * per_device
        assert [r.rank for r in ranks] == list(range(world))
        assert all(r.world_size == world and r.env_vars["WORLD_SIZE"] == str(world) for r in ranks)
        assert all(r.env_vars["RANK"] == str(r.rank) for r in ranks)
        # Each listed device hosts exactly per_device (<= max) contiguous ranks, in listed order.
        held = [(r.cpu_slots if on_cpu else r.global_devices) for r in ranks]
        assert held == [(d,) for d in devices for _ in range(per_device)]
        assert max(Counter(held).values()) <= max_procs
        for r in ranks:
            device = held[r.rank][0]
            assert 0 <= device < len(locations)
            assert r.node_index == locations[device][0]
            if on_cpu:
                assert r.local_devices == () and "CUDA_VISIBLE_DEVICES" not in r.env_vars
            else:
                assert r.local_devices == (locations[device][1],)
                assert r.env_vars["CUDA_VISIBLE_DEVICES"] == str(locations[device][1])
        # LOCAL_RANK on each node is 0..k-1 in rank order, with LOCAL_WORLD_SIZE k.
        for node in {r.node_index for r in ranks}:
            on_node = [r for r in ranks if r.node_index == node]
            assert [r.env_vars["LOCAL_RANK"] for r in on_node] == [str(i) for i in range(len(on_node))]
            assert {r.env_vars["LOCAL_WORLD_SIZE"] for r in on_node} == {str(len(on_node))}
        assert plan.devices_of(name) == tuple(sorted(devices))
        for d in devices:
            assert name in plan.components_on_device(d)
    names = list(plan.components)
    pairwise = set()
    for a in names:
        for b in names:
            assert plan.relation(a, b) == plan.relation(b, a)
            shares = bool(set(plan.devices_of(a)) & set(plan.devices_of(b)))
            assert plan.relation(a, b) == ("collocated" if shares or a == b else "disaggregated")
            if a < b:
                pairwise.add(plan.relation(a, b))
    if pairwise in (set(), {"collocated"}):
        assert plan.mode == "collocated"
    elif pairwise == {"disaggregated"}:
        assert plan.mode == "disaggregated"
    else:
        assert plan.mode == "hybrid"


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 3), st.integers(1, 4), st.integers(0, 20))
def test_any_missing_device_is_reported_by_index(num_nodes, gpus, index):
    inventory = ClusterInventory.with_gpus(num_nodes, gpus)
    total = num_nodes * gpus
    if index < total:
        assert place(inventory, {"actor": str(index)}).devices_of("actor") == (index,)
    else:
        with pytest.raises(PlacementError, match=rf"^placement for 'actor': device {index} does not exist "):
            place(inventory, {"actor": f"0,{index}"})


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 4), st.integers(1, 6), st.integers(1, 6))
def test_more_processes_per_device_than_allowed_is_always_rejected(num_devices, per_device, max_procs):
    spec = {"env": f"0-{num_devices - 1}:0-{num_devices * per_device - 1}"}
    inventory = ClusterInventory.with_gpus(1, 4)
    if per_device <= max_procs:
        assert place(inventory, spec, max_procs_per_device=max_procs).world_size("env") == num_devices * per_device
    else:
        with pytest.raises(PlacementError, match=rf"puts {per_device} on each device, more than "
                           rf"max_procs_per_device={max_procs}"):
            place(inventory, spec, max_procs_per_device=max_procs)
