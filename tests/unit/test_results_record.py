"""`infinirl record`: a finished run's summary becomes a results entry with command, host and date."""

import json
import os
import subprocess
import time

from infinirl.cli import main
from infinirl.results import RECORDED_SECTION, code_version, format_entry, host_probe, record_run


def test_a_run_summary_is_appended_with_its_command_and_host(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    summary = {"eval_after": 0.96, "iterations": 50, "title": "PPO metaworld:reach-v3 (embodied)",
               "command": "infinirl train ppo_metaworld_reach", "host": host_probe()}
    (run / "summary.json").write_text(json.dumps(summary))
    results = tmp_path / "results.md"
    results.write_text("# Measured results\n\nHand-written entries.\n")
    assert main(["record", str(run), "--to", str(results)]) == 0
    text = results.read_text()
    assert text.startswith("# Measured results\n\nHand-written entries.\n")
    assert RECORDED_SECTION in text and "### PPO metaworld:reach-v3 (embodied)" in text
    assert "Command: `infinirl train ppo_metaworld_reach`." in text and f"{host_probe()['vcpus']} vCPUs" in text
    assert '"eval_after": 0.96' in text
    assert main(["record", str(run), "--to", str(results), "--title", "again"]) == 0
    assert results.read_text().count(RECORDED_SECTION) == 1 and "### again" in results.read_text()


def test_recording_an_unfinished_run_names_the_missing_file(tmp_path, capsys):
    assert main(["record", str(tmp_path), "--to", str(tmp_path / "r.md")]) == 2
    assert "summary.json does not exist" in capsys.readouterr().err


def test_a_benchmarks_saved_output_is_recorded_from_its_last_line(tmp_path):
    output = tmp_path / "bench.txt"
    output.write_text('warming up\nstep 1 of 2\n{"title": "pipeline", "ratios": {"a/b": 1.5}}\n\n')
    results = tmp_path / "r.md"
    assert main(["record", str(output), "--to", str(results)]) == 0
    assert "### pipeline" in results.read_text() and '"a/b": 1.5' in results.read_text()


def test_a_file_without_a_json_result_is_one_line_naming_it(tmp_path, capsys):
    bad = tmp_path / "summary.json"
    for text, fragment in [('{"eval_after": 0.9', "holds no JSON result: it must hold a run's summary.json"),
                           ("", "holds no JSON result"),
                           ("[0.9, 1.0]", "holds a JSON list, not the result object")]:
        bad.write_text(text)
        assert main(["record", str(tmp_path), "--to", str(tmp_path / "r.md")]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and str(bad) in err and fragment in err, err
    assert not (tmp_path / "r.md").exists()


def _git(repo, *args):
    subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@example.com", *args],
                   check=True, capture_output=True)


def test_the_code_version_is_the_checkouts_short_commit_dirty_with_tracked_changes_only(tmp_path):
    repo = tmp_path / "checkout"
    (repo / "pkg").mkdir(parents=True)
    assert code_version(repo) is None  # not a git checkout: no commit rather than a wrong one
    _git(repo, "init", "-q")
    assert code_version(repo) is None  # no commit yet
    (repo / "pkg" / "a.py").write_text("x = 1\n")
    _git(repo, "add", ".")
    _git(repo, "commit", "-qm", "first")
    head = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()
    assert code_version(repo) == head
    (repo / "runs").mkdir()
    (repo / "runs" / "metrics.jsonl").write_text("{}\n")  # an untracked run folder leaves it clean
    assert code_version(repo) == head
    (repo / "pkg" / "a.py").write_text("x = 2\n")
    assert code_version(repo) == f"{head}-dirty"
    # a package inside a repository that is not its own (site-packages under some checkout)
    assert code_version(repo / "pkg") is None


def test_an_entry_carries_the_runs_end_date_and_commit_not_todays(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    summary = {"eval_after": 0.5, "iterations": 4, "title": "toy", "command": "infinirl train toy",
               "host": host_probe(), "date": "2026-01-02", "commit": "abc1234-dirty"}
    (run / "summary.json").write_text(json.dumps(summary))
    entry = record_run(run, tmp_path / "r.md")
    assert "Date: 2026-01-02. Commit: `abc1234-dirty`.\n" in entry
    assert '"commit"' not in entry and '"date"' not in entry  # in the header, not repeated in the JSON
    # an older summary without them: the date it was written, and no commit
    del summary["date"], summary["commit"]
    (run / "summary.json").write_text(json.dumps(summary))
    written = time.time() - 3 * 86400
    os.utime(run / "summary.json", (written, written))
    entry = record_run(run, tmp_path / "r.md")
    assert f"Date: {time.strftime('%Y-%m-%d', time.localtime(written))}.\n" in entry and "Commit" not in entry


def test_a_stopped_run_is_recorded_marked_as_stopped(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps({"iterations": 600, "stopped_at": 150, "eval_after": 0.6,
                                                  "title": "PPO push (embodied)", "command": "infinirl train x"}))
    entry = record_run(run, tmp_path / "r.md")
    assert entry.startswith("### PPO push (embodied) (stopped at iteration 150 of 600)\n")
    assert "Stopped: a signal ended the run after iteration 150 of 600, so this is not the full run" in entry
    finished = format_entry(title="t", command="c", result={"iterations": 600}, host={})
    assert "stopped" not in finished.lower()
