"""WorkerGroup.resize: a running group grows and shrinks; new ranks start like launched ones, removed
ranks' processes end, a rank that fails to start leaves the group as it was."""

import os
import time

import psutil
import pytest

from infinirl.runtime import WorkerError, WorkerGroup, place
from infinirl.runtime.placement import resized_spec
from infinirl.runtime.worker import Worker
from tests.conftest import ship_by_value

ship_by_value(__name__)


class Member(Worker):
    def __init__(self, offset: int, fail_from_rank: int = 99):
        if self.rank >= fail_from_rank:
            raise RuntimeError(f"rank {self.rank} refuses to start")
        self.offset = offset

    def whoami(self):
        return {"rank": self.rank, "world": self.world_size, "offset": self.offset, "pid": os.getpid(),
                "master": (os.environ["MASTER_ADDR"], os.environ["MASTER_PORT"]),
                "env": os.environ.get("SCALING_TEST")}


def gone(pid: int, timeout: float = 30) -> bool:
    deadline = time.monotonic() + timeout
    while psutil.pid_exists(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    return not psutil.pid_exists(pid)


def test_a_group_grows_and_shrinks_while_it_runs(ray_cluster):
    inventory = ray_cluster.inventory
    group = WorkerGroup.launch(Member, "resized", placement=place(inventory, {"resized": "0"}).ranks("resized"),
                               args=(7,), env_vars={"SCALING_TEST": "yes"})
    try:
        first = group.whoami().wait()[0]
        placed = place(inventory, {"resized": resized_spec("0", 3)}).ranks("resized")
        group.resize(3, placement=placed)
        assert group.world_size == 3
        info = group.whoami().wait()
        assert [i["rank"] for i in info] == [0, 1, 2]
        assert info[0]["pid"] == first["pid"]  # rank 0 kept its process
        assert all(i["offset"] == 7 and i["env"] == "yes" for i in info)  # the launch's args and environment
        assert all(i["master"] == first["master"] for i in info)  # one rendezvous for the group
        assert [i["world"] for i in info[1:]] == [3, 3]
        group.resize(1)
        assert group.world_size == 1 and group.whoami().wait()[0]["pid"] == first["pid"]
        assert gone(info[1]["pid"]) and gone(info[2]["pid"])
        with pytest.raises(IndexError, match="rank 1 does not exist"):
            group.call("whoami", ranks=[1])
    finally:
        group.shutdown()


def test_a_rank_that_fails_to_start_leaves_the_group_as_it_was(ray_cluster):
    group = WorkerGroup.launch(Member, "resized-fail", num_ranks=1, args=(0, 2))
    try:
        with pytest.raises(WorkerError, match="rank 2 refuses to start"):
            group.resize(3)
        assert group.world_size == 1
        assert group.whoami().wait()[0]["rank"] == 0
        with pytest.raises(ValueError, match="num_ranks must be an int >= 1"):
            group.resize(0)
    finally:
        group.shutdown()
    with pytest.raises(RuntimeError, match="shut down"):
        group.resize(2)
