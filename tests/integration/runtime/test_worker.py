"""WorkerGroup: launch, fan-out, handles, failures reported at their root, restarts, shutdown."""

import asyncio
import importlib
import os
import socket
import sys
import threading
import time

import psutil
import pytest
import torch

from infinirl.runtime import CallCancelled, Channel, RestartPolicy, Worker, WorkerError, WorkerGroup
from tests.conftest import ship_by_value

ship_by_value(__name__)


class Echo(Worker):
    def __init__(self, offset: int = 0):
        import threading

        self.offset = offset
        self.calls = []
        self.init_thread = threading.get_ident()

    def whoami(self):
        return {"rank": self.rank, "world": self.world_size, "env_rank": os.environ["RANK"],
                "master": (os.environ["MASTER_ADDR"], os.environ["MASTER_PORT"]), "pid": os.getpid()}

    def add(self, x):
        self.calls.append(x)
        return x + self.offset + self.rank

    def order(self):
        return list(self.calls)

    def slow(self, seconds):
        time.sleep(seconds)
        return self.rank

    async def async_double(self, x):
        await asyncio.sleep(0.01)
        return 2 * x

    def initial_environ(self):
        """The environment the process started with (/proc/self/environ is not changed by os.environ)."""
        with open("/proc/self/environ", "rb") as f:
            return dict(item.decode().split("=", 1) for item in f.read().split(b"\0") if b"=" in item)

    def on_compute_thread(self):
        from infinirl.runtime.compute_thread import on_compute_thread

        return on_compute_thread()

    def constructed_on_this_thread(self):
        import threading

        return self.init_thread == threading.get_ident()

    async def async_on_compute_thread(self):
        from infinirl.runtime.compute_thread import on_compute_thread

        return on_compute_thread()

    def fail_on(self, bad_rank):
        if self.rank == bad_rank:
            raise ValueError(f"boom from rank {self.rank}")
        time.sleep(30)  # a healthy rank stuck in a "collective": the error must not wait for it
        return "ok"

    def take(self, ch: Channel, started: Channel):
        started.put(self.rank)
        return ch.get()

    async def take_async(self, ch: Channel, started: Channel):
        await started.put_async(self.rank)
        return await ch.get_async()

    def make_lock(self):
        return threading.Lock()  # cannot be pickled

    def allreduce(self):
        import torch.distributed as dist

        self.init_process_group()
        t = torch.tensor([float(self.rank + 1)])
        dist.all_reduce(t)
        return float(t.item())


    def die_in_allreduce(self, dying_rank):
        """Forms the group, then one rank crashes while its peers wait for it in a collective.

        The dying rank closes its group's connections half a second before it crashes: its peers'
        gloo error then reaches the driver before Ray reports the death, every time (a process
        that just dies makes the same order a race, which gloo's ~20 ms often wins)."""
        import faulthandler

        import torch.distributed as dist

        self.init_process_group(timeout_s=60)
        if self.rank == dying_rank:
            dist.destroy_process_group()
            time.sleep(0.5)
            faulthandler._sigsegv()
        t = torch.tensor([1.0])
        dist.all_reduce(t)
        return float(t.item())


class BadInit(Worker):
    def __init__(self):
        if self.rank == 1:
            raise RuntimeError("cannot open device")


def test_launch_fanout_and_chosen_ranks(ray_cluster):
    group = WorkerGroup.launch(Echo, "echo", num_ranks=3, kwargs={"offset": 10})
    try:
        info = group.whoami().wait()
        assert [i["rank"] for i in info] == [0, 1, 2]
        assert {i["world"] for i in info} == {3}
        assert [i["env_rank"] for i in info] == ["0", "1", "2"]
        assert len({i["master"] for i in info}) == 1
        assert group.add(5).wait() == [15, 16, 17]
        assert group.call("add", 1, ranks=[2]).wait() == [13]
        assert group.call_each("add", [(0,), (100,), (200,)]).wait() == [10, 111, 212]
        assert asyncio.run(_await(group.async_double(21))) == [42, 42, 42]
    finally:
        group.shutdown()


async def _await(handle):
    return await handle


def test_sync_calls_run_in_call_order(ray_cluster):
    group = WorkerGroup.launch(Echo, "ordered", num_ranks=1)
    try:
        handles = [group.add(i) for i in range(50)]
        [h.wait() for h in handles]
        assert group.order().wait()[0] == list(range(50))
    finally:
        group.shutdown()


def test_sync_methods_run_on_the_compute_thread_and_async_ones_do_not(ray_cluster):
    """The thread process-wide torch state may be changed from (compiled_step's guard skipping)."""
    group = WorkerGroup.launch(Echo, "threads", num_ranks=1)
    try:
        assert group.async_on_compute_thread().wait() == [False]  # the event loop's (main) thread
        assert group.on_compute_thread().wait() == [True]
        # the constructor too: parallel torch work on a second thread throttles libgomp's spinning
        assert group.constructed_on_this_thread().wait() == [True]
    finally:
        group.shutdown()


def test_launch_env_vars_are_set_from_the_process_start(ray_cluster):
    """What OpenMP reads when torch loads (spin_wait_env) must be there before any import."""
    group = WorkerGroup.launch(Echo, "env_at_start", num_ranks=1, env_vars={"GOMP_SPINCOUNT": "12345"})
    try:
        start = group.initial_environ().wait()[0]
        assert start["GOMP_SPINCOUNT"] == "12345"
        assert start["OMP_WAIT_POLICY"] == "PASSIVE"  # the workers' defaults stay
        assert start["HF_HUB_DISABLE_PROGRESS_BARS"] == "1"  # no worker progress bar in the driver's terminal
    finally:
        group.shutdown()


def test_handle_done_and_timeout(ray_cluster):
    group = WorkerGroup.launch(Echo, "timing", num_ranks=2)
    try:
        handle = group.slow(1.0)
        assert not handle.done()
        with pytest.raises(TimeoutError, match=r"slow\(\) not finished"):
            handle.wait(timeout=0.05)
        assert handle.wait(timeout=30) == [0, 1]
        assert handle.done()
    finally:
        group.shutdown()


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_cancel_frees_ranks_blocked_in_a_channel_for_later_calls(ray_cluster):
    """A call that can never finish (its producer is gone) is cancelled; the calls queued behind
    it on the same ranks run, and the cancelled gets took nothing from the channel."""
    tag = time.time_ns()
    ch, started = Channel.create(f"cancel-{tag}"), Channel.create(f"cancel-started-{tag}")
    group = WorkerGroup.launch(Echo, "cancel", num_ranks=2)
    try:
        # Rounds, because the cancel can reach a get before or after the get reaches the channel.
        for round_ in range(4):
            for method in ("take", "take_async"):
                blocked = group.call(method, ch, started)
                assert sorted(started.get(timeout=60) for _ in range(2)) == [0, 1]  # both ranks wait in ch.get
                queued = group.add(1)  # on each rank's compute thread, behind a blocked sync call
                blocked.cancel()
                with pytest.raises(CallCancelled, match=r"cancel\[rank \d\]\.take(_async)?\(\) was cancelled"):
                    blocked.wait(timeout=60)
                assert queued.wait(timeout=60) == [1, 2]
                assert group.add(5).wait(timeout=60) == [5, 6]
                ch.put(f"kept {round_}")
                assert ch.get(timeout=30) == f"kept {round_}", f"a cancelled {method} took the item"
        assert ch.qsize() == 0
    finally:
        group.shutdown()


def test_an_unserialisable_result_is_reported_and_the_rank_stays_usable(ray_cluster):
    group = WorkerGroup.launch(Echo, "unpicklable", num_ranks=1)
    try:
        with pytest.raises(WorkerError) as info:
            group.make_lock().wait(timeout=60)
        text = str(info.value)
        assert ("unpicklable[rank 0].make_lock() returned a value of type _thread.lock that could not be "
                "serialised") in text
        assert "cannot pickle '_thread.lock' object" in text
        assert "died" not in text and "process exited" not in text
        assert group.add(1).wait(timeout=60) == [1]
        # An argument Ray cannot send: the call is never submitted, and its number in the rank's
        # call order must not make every later call wait for it.
        with pytest.raises(Exception, match="pickle"):
            group.add(threading.Lock())
        assert group.add(2).wait(timeout=60) == [2]
    finally:
        group.shutdown()


def test_a_call_ray_fails_before_it_runs_does_not_hold_up_later_calls(ray_cluster, tmp_path, monkeypatch):
    """An argument the rank cannot unpickle fails inside Ray, before the call takes its turn in the
    rank's call order: later calls must run without anyone waiting on the failed one."""
    module = f"driver_only_{time.time_ns()}"
    (tmp_path / f"{module}.py").write_text("class OnlyOnTheDriver:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))  # importable here, not in the rank's process
    monkeypatch.delitem(sys.modules, module, raising=False)
    only_here = importlib.import_module(module).OnlyOnTheDriver()
    group = WorkerGroup.launch(Echo, "unimportable", num_ranks=1)
    try:
        failed = group.add(only_here)
        assert group.add(1).wait(timeout=60) == [1]  # without a wait on the failed call first
        assert group.async_double(2).wait(timeout=60) == [4]
        with pytest.raises(WorkerError, match=module):
            failed.wait(timeout=60)
        assert group.add(2).wait(timeout=60) == [2]
    finally:
        group.shutdown()
        sys.modules.pop(module, None)


def test_a_component_name_belongs_to_one_live_group(ray_cluster):
    first = WorkerGroup.launch(Echo, "unique", num_ranks=1)
    try:
        with pytest.raises(ValueError, match="a WorkerGroup named 'unique' is already running"):
            WorkerGroup.launch(Echo, "unique", num_ranks=1)
        assert first.add(1).wait(timeout=60) == [1]  # the running group is untouched
    finally:
        first.shutdown()
    second = WorkerGroup.launch(Echo, "unique", num_ranks=1)  # shut down: the name is free again
    second.shutdown()


def test_torch_distributed_group_forms(ray_cluster):
    group = WorkerGroup.launch(Echo, "dist", num_ranks=2)
    try:
        assert group.allreduce().wait(timeout=120) == [3.0, 3.0]
    finally:
        group.shutdown()


@pytest.mark.parametrize("how", ["wait", "await"])
def test_a_rank_that_dies_in_a_collective_is_reported_not_its_peers_error(ray_cluster, deliberate_deaths, how):
    """gloo tells a peer "Connection closed by peer" within milliseconds, before Ray reports the
    death (about a second): the error must name the rank that died, with its crash, not the peer."""
    group = WorkerGroup.launch(Echo, f"collective_{how}", num_ranks=3)
    deliberate_deaths(*group.pids())
    try:
        handle = group.die_in_allreduce(2)
        with pytest.raises(WorkerError) as info:
            handle.wait(timeout=120) if how == "wait" else asyncio.run(asyncio.wait_for(_await(handle), 120))
        err = info.value
        text = str(err)
        assert err.rank == 2 and "died (process exited)" in text, text
        assert "Segmentation fault" in text and "die_in_allreduce" in text  # its crash log
        peer = err.__cause__  # what the peers saw, kept
        assert isinstance(peer, WorkerError) and peer.rank in (0, 1) and peer.cause == "raised", repr(peer)
    finally:
        group.shutdown()
        _remove_crash_logs(group)


def test_the_rendezvous_port_is_held_from_launch_so_no_one_else_can_take_it(ray_cluster):
    """A port found free at launch and bound only when the group forms (maybe much later) can be
    taken meanwhile by another group or program: rank 0 would fail to bind it, or the other ranks
    would meet a stranger. Rank 0 holds the port from its start, so the group still forms."""
    group = WorkerGroup.launch(Echo, "rendezvous", num_ranks=2)
    squatter = socket.socket()
    try:
        port = int(group.whoami().wait(timeout=60)[0]["master"][1])
        with pytest.raises(OSError):  # held by rank 0's rendezvous store
            squatter.bind(("", port))
            squatter.listen()
        assert group.allreduce().wait(timeout=120) == [3.0, 3.0]
    finally:
        squatter.close()
        group.shutdown()


def test_exception_names_component_rank_node_and_traceback(ray_cluster):
    group = WorkerGroup.launch(Echo, "trainer", num_ranks=2)
    try:
        start = time.monotonic()
        with pytest.raises(WorkerError) as info:
            group.fail_on(1).wait()
        assert time.monotonic() - start < 20, "the failure must surface before healthy ranks finish"
        err = info.value
        assert err.component == "trainer" and err.rank == 1 and err.method == "fail_on"
        text = str(err)
        assert "trainer[rank 1].fail_on()" in text
        assert "boom from rank 1" in text and "ValueError" in text
        assert "Traceback" in text and "in fail_on" in text
        assert err.node_ip and "actor died" not in text.lower()
    finally:
        group.shutdown()


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_init_failure_is_reported_with_rank(ray_cluster):
    from infinirl.runtime.worker import CRASH_LOG_DIR

    with pytest.raises(WorkerError) as info:
        WorkerGroup.launch(BadInit, "badinit", num_ranks=2)
    assert info.value.rank == 1 and info.value.method == "__init__"
    assert "cannot open device" in str(info.value)
    assert not list(CRASH_LOG_DIR.glob("badinit-rank*"))  # nothing left of the failed launch


def test_unknown_method_is_rejected_before_dispatch(ray_cluster):
    group = WorkerGroup.launch(Echo, "actor", num_ranks=1)
    try:
        with pytest.raises(AttributeError, match=r"no method 'ad'.*Did you mean 'add'"):
            group.ad(1)
        with pytest.raises(AttributeError, match="has no method 'nope'"):
            group.call("nope")
        with pytest.raises(IndexError, match="rank 5 does not exist"):
            group.call("add", 1, ranks=[5])
    finally:
        group.shutdown()


class Crashy(Worker):
    """Dies hard (no Python exception) the first time; a marker file survives the restart."""

    def __init__(self, marker: str):
        self.marker = marker

    def work(self, x):
        if not os.path.exists(self.marker):
            open(self.marker, "w").close()
            os._exit(3)
        return x * 2

    def crash_always(self):
        os._exit(4)


class SegfaultsInInit(Worker):
    def __init__(self):
        import faulthandler

        faulthandler._sigsegv()


def test_a_segfault_in_the_constructor_is_reported_with_its_stack(ray_cluster):
    from infinirl.runtime.worker import CRASH_LOG_DIR

    try:
        with pytest.raises(WorkerError) as info:
            WorkerGroup.launch(SegfaultsInInit, "initsegv", num_ranks=1, ready_timeout_s=120)
        text = str(info.value)
        assert info.value.method == "__init__" and "Segmentation fault" in text and "__init__" in text
    finally:
        for log in CRASH_LOG_DIR.glob("initsegv-rank*"):
            log.unlink()


class Segfaults(Worker):
    """Dies of a real segmentation fault, in one of two methods (to tell the crashes apart)."""

    def crash_first(self):
        import faulthandler

        faulthandler._sigsegv()

    def crash_second(self):
        import faulthandler

        faulthandler._sigsegv()

    def pid(self):
        return os.getpid()


def test_a_segfault_is_reported_with_the_python_stack_of_the_crash(ray_cluster, deliberate_deaths):
    group = WorkerGroup.launch(Segfaults, "sim", num_ranks=1)
    deliberate_deaths(*group.pids())
    try:
        with pytest.raises(WorkerError) as info:
            group.crash_first().wait(timeout=120)
        text = str(info.value)
        assert "Segmentation fault" in text and "crash_first" in text
    finally:
        group.shutdown()
        _remove_crash_logs(group)


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_a_restarted_rank_that_crashes_again_is_reported_with_its_own_crash(ray_cluster, deliberate_deaths):
    """The crash log quoted is the one of the process that died last, not of the first one."""
    group = WorkerGroup.launch(Segfaults, "sim2", num_ranks=1, restart=RestartPolicy(max_restarts=1, retry_calls=False))
    try:
        first_pid = group.pid().wait()[0]
        deliberate_deaths(first_pid)
        with pytest.raises(WorkerError):
            group.crash_first().wait(timeout=120)
        deadline = time.monotonic() + 60
        while True:  # calls fail while Ray restarts the process
            try:
                second_pid = group.pid().wait(timeout=30)[0]
                if second_pid != first_pid:
                    deliberate_deaths(second_pid)
                    break
            except WorkerError:
                pass
            assert time.monotonic() < deadline, "the rank was not restarted"
            time.sleep(0.5)
        with pytest.raises(WorkerError) as info:
            group.crash_second().wait(timeout=120)  # the restarted process
        text = str(info.value)
        assert "crash_second" in text and "crash_first" not in text
        assert info.value.pid not in (None, first_pid)  # the process that died last
    finally:
        group.shutdown()
        _remove_crash_logs(group)


def _remove_crash_logs(group):
    """A log with a crash in it outlives shutdown, for the user; tests clean up their own."""
    for info in group.rank_info:
        if os.path.exists(info["crash_log"]):
            os.unlink(info["crash_log"])


def test_restart_policy_restarts_and_retries(ray_cluster, tmp_path, deliberate_deaths):
    group = WorkerGroup.launch(Crashy, "env", num_ranks=1, args=(str(tmp_path / "m"),),
                               restart=RestartPolicy(max_restarts=2))
    deliberate_deaths(*group.pids())
    try:
        assert group.work(21).wait(timeout=120) == [42]
    finally:
        group.shutdown()


def test_dead_process_reported_as_root_cause(ray_cluster, tmp_path, deliberate_deaths):
    group = WorkerGroup.launch(Crashy, "robot", num_ranks=1, args=(str(tmp_path / "m"),))
    deliberate_deaths(*group.pids())
    try:
        with pytest.raises(WorkerError) as info:
            group.crash_always().wait(timeout=120)
        assert info.value.component == "robot" and info.value.rank == 0
        assert "died" in str(info.value) and "crash_always" in str(info.value)
    finally:
        group.shutdown()


def test_shutdown_leaves_no_worker_process(ray_cluster):
    group = WorkerGroup.launch(Echo, "gone", num_ranks=2)
    pids = [i["pid"] for i in group.whoami().wait()]
    group.shutdown()
    deadline = time.monotonic() + 20
    while any(psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE for p in pids):
        assert time.monotonic() < deadline, f"worker processes {pids} still alive after shutdown"
        time.sleep(0.2)


def test_a_group_dropped_without_shutdown_leaves_no_crash_log(ray_cluster):
    """A program that loses its last reference to a group (Ray then ends the ranks) must not leave
    the ranks' empty crash logs behind either."""
    import gc

    group = WorkerGroup.launch(Echo, "dropped", num_ranks=1)
    logs = [info["crash_log"] for info in group.rank_info]
    assert all(os.path.exists(path) for path in logs)
    del group
    gc.collect()
    assert not any(os.path.exists(path) for path in logs)


def test_shutdown_removes_empty_crash_logs_and_keeps_one_with_a_crash(ray_cluster):
    """One crash log per worker process: left behind, they pile up in the temp dir by thousands."""
    group = WorkerGroup.launch(Echo, "logs", num_ranks=2)
    logs = [info["crash_log"] for info in group.rank_info]
    assert all(os.path.exists(path) for path in logs)
    with open(logs[1], "a") as log:
        log.write("Fatal Python error: Segmentation fault\n")  # as faulthandler would
    try:
        group.shutdown()
        assert not os.path.exists(logs[0])
        assert os.path.exists(logs[1])
    finally:
        if os.path.exists(logs[1]):
            os.unlink(logs[1])


def test_raylet_reports_of_deliberate_deaths_are_dropped_and_others_kept(ray_cluster, deliberate_deaths, capsys):
    """Ray's driver prints the raylet's "A worker died ..." messages (see this directory's
    conftest); the ones about processes a test killed on purpose stay out of the output."""
    import random
    import string

    import ray._private.worker as ray_worker

    # Ray prints a raylet message only the first time its digit-free words occur: make them new.
    unique = "".join(random.choices(string.ascii_letters, k=24))

    def raylet_says(pid: int) -> None:
        line = (f"A worker died or was killed while executing a task by an unexpected system error. {unique} "
                f"Worker PID: {pid} Worker exit type: SYSTEM_ERROR (1) the process was killed by the OOM killer")
        ray_worker.print_to_stdstream({"lines": [line], "pid": "raylet", "is_err": False}, ignore_prefix=False)

    deliberate_deaths(4_000_001)
    raylet_says(4_000_001)
    raylet_says(4_000_002)
    out = capsys.readouterr().out
    assert "Worker PID: 4000002" in out and "Worker PID: 4000001" not in out


def test_calls_from_two_driver_threads_all_complete(ray_cluster):
    """Each call takes the next number of its rank's call order: two threads that took the same
    number would leave a later one unused, and every call behind it would wait for it forever."""
    group = WorkerGroup.launch(Echo, "two_threads", num_ranks=1)
    old_interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible, inside the numbering too
    try:
        handles: list = []
        threads = [threading.Thread(target=lambda: handles.extend(group.add(i) for i in range(100)))
                   for _ in range(2)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    finally:
        sys.setswitchinterval(old_interval)
    assert len(handles) == 200
    for handle in handles:
        handle.wait(timeout=30)
    assert len(group.order().wait()[0]) == 200
    group.shutdown()
