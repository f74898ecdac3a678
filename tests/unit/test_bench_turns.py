"""The benchmark's turn-taking (benchmarks/_bench_turns.py): rows side by side never run at once.

What makes an interleaved benchmark fair is that a row's measured work never overlaps another row's
(they would compete for the cores) nor its start-up or post-run work. These rows are tiny Python
processes that stamp each turn's start and end, so the test checks the protocol, not timings."""

import json
import os
import subprocess
import sys

import pytest

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

from _bench_turns import Conductor, RowFailed  # noqa: E402

ROW = """
import json, sys, time
sys.path.insert(0, {benchmarks!r})
from _bench_turns import Turn
turn = Turn.from_env()
time.sleep({startup})                          # start-up: before the first turn
ready = time.monotonic()
stamps = []
for i in range({turns}):
    with turn:
        start = time.monotonic()
        if i == {fail_at}:
            raise RuntimeError("row {name} broke on turn %d" % i)
        time.sleep(0.02)
        stamps.append((start, time.monotonic()))
turn.take()                                    # the post-loop turn
print(json.dumps({{"ready": ready, "stamps": stamps, "after": time.monotonic()}}))
"""


def row(name: str, turns: int, startup: float = 0.0, fail_at: int = -1) -> list[str]:
    return [sys.executable, "-c", ROW.format(benchmarks=BENCHMARKS, startup=startup, turns=turns, fail_at=fail_at,
                                             name=name)]


def test_rows_take_turns_in_rotation_and_never_overlap():
    names, turns = ["a", "b", "c"], 4
    # c starts slowly: no turn may begin before every row is ready
    conductor = Conductor({n: row(n, turns, startup=0.5 if n == "c" else 0.0) for n in names})
    out = {n: json.loads(text.strip().splitlines()[-1]) for n, text in conductor.run(turns).items()}
    spans = sorted((start, end, n, i) for n in names for i, (start, end) in enumerate(out[n]["stamps"]))
    assert len(spans) == 3 * turns
    for (_s0, e0, *_), (s1, _e1, *_) in zip(spans, spans[1:]):
        assert e0 <= s1, "two rows ran at once"
    assert spans[0][0] >= max(out[n]["ready"] for n in names), "a turn overlapped a row's start-up"
    # cycle i runs the rows in the order rotated by i, each row's turns in its own order
    order = [n for *_, n, _ in spans]
    assert order == ["a", "b", "c", "b", "c", "a", "c", "a", "b", "a", "b", "c"]
    assert [i for *_, n, i in spans if n == "a"] == list(range(turns))
    # the post-loop work comes after every measured turn of every row
    last_end = spans[-1][1]
    assert all(out[n]["after"] >= last_end for n in names)


def test_a_failing_row_is_reported_with_its_traceback_and_the_others_are_stopped():
    conductor = Conductor({"good": row("good", 5), "bad": row("bad", 5, fail_at=2)})
    with pytest.raises(RowFailed) as error:
        conductor.run(5)
    message = str(error.value)
    assert "row bad exited" in message and "row bad broke on turn 2" in message
    assert all(r.process.poll() is not None for r in conductor.rows)


def test_a_row_started_without_a_conductor_runs_freely():
    env = {k: v for k, v in os.environ.items() if k != "INFINIRL_BENCH_TURNS"}
    script = f"import sys; sys.path.insert(0, {BENCHMARKS!r}); from _bench_turns import Turn; print(Turn.from_env())"
    assert subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True,
                          check=True).stdout.strip() == "None"


TICKER = """
import sys, time
with open(sys.argv[1], "a", buffering=1) as out:
    while True:
        out.write(f"{time.monotonic()}\\n")
        time.sleep(0.002)
"""

BUSY_ROW = """
import subprocess, sys, time
sys.path.insert(0, {benchmarks!r})
from _bench_turns import Turn
turn = Turn.from_env()
# a child in a process group of its own (as Ray's workers are): it ticks all the time unless frozen
child = subprocess.Popen([sys.executable, "-c", {ticker!r}, {ticks!r}], process_group=0)
time.sleep(0.3)
for i in range({turns}):
    with turn:
        time.sleep(0.05)
turn.take()
child.kill()
"""


def test_a_waiting_row_and_every_process_it_started_are_frozen(tmp_path):
    """A waiting row's processes (a Ray instance's keep waking up) take no CPU during another's turn."""
    ticks, turns = tmp_path / "ticks", 3
    busy = [sys.executable, "-c", BUSY_ROW.format(benchmarks=BENCHMARKS, ticker=TICKER, ticks=str(ticks), turns=turns)]
    quiet = [sys.executable, "-c", ROW.format(benchmarks=BENCHMARKS, startup=0.0, turns=turns, fail_at=-1, name="quiet")
             .replace("time.sleep(0.02)", "time.sleep(0.3)")]
    out = Conductor({"busy": busy, "quiet": quiet}).run(turns)
    spans = json.loads(out["quiet"].strip().splitlines()[-1])["stamps"]
    stamps = [float(line) for line in ticks.read_text().split()]
    assert len(stamps) > 50  # it did tick while its row ran
    for start, end in spans:
        inside = [t for t in stamps if start + 0.01 < t < end]
        assert not inside, f"the waiting row's child ran during the other row's turn ({len(inside)} ticks)"


def test_the_embodied_gate_wraps_the_method_the_run_loop_calls_once_per_iteration(monkeypatch):
    """embodied_pipeline.py's runner rows take one turn per iteration through this gate; a gate
    that patched a method the loop no longer calls crashed every row at start."""
    import _bench_turns

    from infinirl.runners.embodied import EmbodiedFlow
    from infinirl.runners.loop import Flow

    assert callable(getattr(Flow, _bench_turns.EMBODIED_STEP, None)), "the run loop's per-iteration call"
    original = getattr(EmbodiedFlow, _bench_turns.EMBODIED_STEP)
    monkeypatch.setattr(EmbodiedFlow, _bench_turns.EMBODIED_STEP, original)  # restored after the test
    read_fd, write_fd = os.pipe()
    monkeypatch.setenv("INFINIRL_BENCH_TURNS", f"{read_fd},{write_fd}")
    try:
        _bench_turns.gate_embodied_runner()
        gated = getattr(EmbodiedFlow, _bench_turns.EMBODIED_STEP)
        assert gated is not original and gated.__wrapped__ is original
    finally:
        os.close(read_fd)
        os.close(write_fd)


def test_the_embodied_gate_names_a_missing_method_before_any_turn(monkeypatch):
    import _bench_turns

    from infinirl.runners.embodied import EmbodiedFlow

    monkeypatch.delattr(EmbodiedFlow, _bench_turns.EMBODIED_STEP)
    monkeypatch.setenv("INFINIRL_BENCH_TURNS", "0,1")  # never used: the gate fails first
    with pytest.raises(RuntimeError, match="EmbodiedFlow has no method 'step'"):
        _bench_turns.gate_embodied_runner()
