"""`infinirl record`: a finished run's summary becomes a results entry with command, host and date."""

import json

from infinirl.cli import main
from infinirl.results import RECORDED_SECTION, host_probe


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
