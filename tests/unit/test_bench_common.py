"""How every benchmark ends (benchmarks/_bench_common.py): one final JSON line, always, with the
failures that void it, and exit status 1 when there is any; a crash it did not expect still ends
in that line, so a script that reads the last line never parses a traceback or finds nothing."""

import json
import os
import sys

import pytest

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

import _bench_common as bc  # noqa: E402


def last_line(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_failed_sides_are_failures_and_skipped_ones_are_not():
    results = {"ours": {"rate": 2.0}, "lerobot": {"skipped": "not installed"}, "ray": bc.side_failed("exit 1"),
               "note": "text"}
    assert bc.failures_of(results) == ["ray: exit 1"]


def test_a_run_with_failures_prints_them_last_and_exits_1_unrecorded(capsys, tmp_path):
    record = tmp_path / "results.md"
    assert bc.conclude({"benchmark": "b", "ratios": {"x": None}}, ["ray: exit 1"], record=(str(record), "B")) == 1
    assert last_line(capsys) == {"benchmark": "b", "ratios": {"x": None}, "failures": ["ray: exit 1"]}
    assert not record.exists()
    assert bc.conclude({"benchmark": "b", "ratios": {"x": 2.0}}) == 0
    assert last_line(capsys)["failures"] == []


def test_an_unexpected_crash_still_ends_in_the_final_line_and_argument_errors_pass_through(capsys):
    def crashes():
        print("partial output")
        raise KeyError("median_s")

    assert bc.concluded("b", crashes) == 1
    assert last_line(capsys) == {"benchmark": "b", "ratios": {}, "failures": ["KeyError: 'median_s'"]}

    def bad_argument():
        raise SystemExit(2)

    with pytest.raises(SystemExit):
        bc.concluded("b", bad_argument)
    assert bc.concluded("b", lambda: None) == 0


def test_a_recorded_benchmark_names_the_commit_it_ran_from(tmp_path, capsys):
    from infinirl.results import code_version

    record = tmp_path / "results.md"
    assert bc.conclude({"benchmark": "b", "ratios": {"x": 2.0}}, record=(str(record), "B")) == 0
    commit = code_version()
    text = record.read_text()
    assert "### B\n" in text
    assert (f"Commit: `{commit}`." in text) if commit else ("Commit" not in text)
