"""CallOrder: calls of one caller start in their numbered order; a cancelled call gives its turn up."""

import asyncio

from infinirl.runtime.call_order import CallOrder

# A broken CallOrder makes a call wait forever: every wait here is bounded so the test fails instead.


async def _settle() -> None:
    for _ in range(5):  # let every waiting task run up to its next wait
        await asyncio.sleep(0)


def _run_calls(order: CallOrder, started: list, caller: str, seqs: list[int]) -> dict[int, asyncio.Task]:
    async def call(seq: int) -> None:
        await order.wait_turn(caller, seq)
        started.append(seq)
        order.end_turn(caller, seq)

    return {seq: asyncio.ensure_future(call(seq)) for seq in seqs}


def test_calls_start_in_order_whatever_order_they_arrive_in():
    async def main():
        order, started = CallOrder(), []
        tasks = _run_calls(order, started, "c", [3, 1, 2, 0])
        await asyncio.wait_for(asyncio.gather(*tasks.values()), 30)
        return started

    assert asyncio.run(main()) == [0, 1, 2, 3]


def test_a_call_cancelled_before_its_turn_gives_the_turn_up():
    """Without this, every later call of the caller would wait forever behind the cancelled one."""

    async def main():
        order, started = CallOrder(), []
        tasks = _run_calls(order, started, "c", [1, 2, 3])
        await _settle()
        tasks[2].cancel()  # waits for its turn (call 1 has not started either)
        other = _run_calls(order, started, "other", [0])  # another caller is not affected
        await _settle()
        tasks.update(_run_calls(order, started, "c", [0]))
        await asyncio.wait_for(asyncio.gather(*(t for seq, t in tasks.items() if seq != 2), *other.values()), 30)
        return started, tasks[2].cancelled()

    started, cancelled = asyncio.run(main())
    assert cancelled
    assert started.count(0) == 2  # call 0 of each caller
    assert [s for s in started if s != 0] == [1, 3]  # call 2 never ran, call 3 did not wait for it


def test_a_call_cancelled_when_its_turn_came_hands_it_on():
    async def main():
        order, started = CallOrder(), []
        tasks = _run_calls(order, started, "c", [1, 2])
        await _settle()
        order.end_turn("c", 0)  # call 0 started elsewhere: call 1's turn is granted...
        tasks[1].cancel()  # ...but it is cancelled before it runs
        await asyncio.wait_for(tasks[2], 30)
        return started

    assert asyncio.run(main()) == [2]


def test_a_restarted_actor_resumes_a_callers_numbering():
    async def main():
        order = CallOrder()
        await asyncio.wait_for(order.wait_turn("c", 7, resume=True), 30)  # not seen before: its turn now
        order.end_turn("c", 7)
        await asyncio.wait_for(order.wait_turn("c", 8, resume=True), 30)

    asyncio.run(main())


def test_a_call_given_up_before_it_arrived_neither_blocks_later_calls_nor_runs():
    """Ray could not submit or deliver call 1 (or it was cancelled on its way): ``skip``."""

    async def main():
        order, started = CallOrder(), []
        tasks = _run_calls(order, started, "c", [0, 2])
        await _settle()
        assert started == [0]  # call 2 waits for call 1
        order.skip("c", 1)
        await asyncio.wait_for(asyncio.gather(*tasks.values()), 30)
        late = _run_calls(order, started, "c", [1])[1]  # should it arrive after all, it does not run
        await asyncio.wait([late], timeout=30)
        return started, late.cancelled()

    started, cancelled = asyncio.run(main())
    assert started == [0, 2] and cancelled


def test_skipping_a_call_that_started_or_waits_changes_nothing():
    async def main():
        order, started = CallOrder(), []
        tasks = _run_calls(order, started, "c", [0, 2, 1])
        await _settle()
        order.skip("c", 0)  # started
        order.skip("c", 2)  # arrived, waiting: it runs in its turn
        await asyncio.wait_for(asyncio.gather(*tasks.values()), 30)
        return started

    assert asyncio.run(main()) == [0, 1, 2]


def test_a_retried_call_arriving_behind_a_later_one_after_a_restart_runs():
    """A restarted actor continues at the first number it sees; an earlier one retried behind it
    must not wait for a turn that has passed."""

    async def main():
        order, started = CallOrder(), []

        async def call(seq: int) -> None:
            await order.wait_turn("c", seq, resume=True)
            started.append(seq)
            order.end_turn("c", seq)

        await asyncio.wait_for(call(8), 30)
        await asyncio.wait_for(call(7), 30)
        return started

    assert asyncio.run(main()) == [8, 7]


def test_a_skip_that_reaches_a_restarted_actor_first_keeps_the_callers_numbering():
    """Ray failed call 7 outside the method (the driver skips every such call) after the actor
    restarted: call 8 still resumes the numbering, instead of waiting for turns 0-7."""

    async def main():
        order = CallOrder()
        order.skip("c", 7)
        await asyncio.wait_for(order.wait_turn("c", 8, resume=True), 30)
        order.end_turn("c", 8)
        late = asyncio.ensure_future(order.wait_turn("c", 7, resume=True))  # arriving after all
        await asyncio.wait([late], timeout=30)
        return late.cancelled()

    assert asyncio.run(main())


def test_a_skip_that_arrives_before_a_callers_first_call_lets_the_next_one_start():
    async def main():
        order, started = CallOrder(), []
        order.skip("c", 0)
        await asyncio.wait_for(asyncio.gather(*_run_calls(order, started, "c", [1]).values()), 30)
        return started

    assert asyncio.run(main()) == [1]
