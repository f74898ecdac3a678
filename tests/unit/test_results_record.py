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
