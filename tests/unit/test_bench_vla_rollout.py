"""The π0 rollout benchmark's summaries (benchmarks/vla_rollout.py): rates, the ratio, the action
agreement that shows both sides did the same work, and which reference interpreter is used."""

import os
import statistics
import sys

import pytest

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "benchmarks")
sys.path.insert(0, BENCHMARKS)

from vla_rollout import (  # noqa: E402
    SIZES,
    act_ratio,
    action_agreement,
    compare_actions,
    final_line,
    resolve_reference_python,
    run_failures,
    timing_summary,
)


def test_timing_summary_is_the_median_call_and_batch_over_it():
    seconds = [0.5, 0.2, 0.4, 10.0]  # an outlier moves the mean, not the median
    summary = timing_summary(seconds, batch_size=4)
    assert summary["median_s"] == pytest.approx(statistics.median(seconds)) == pytest.approx(0.45)
    assert summary["chunks_per_s"] == pytest.approx(4 / 0.45, abs=1e-4)
    assert (summary["min_s"], summary["max_s"], summary["repeats"]) == (0.2, 10.0, 4)
    with pytest.raises(ValueError, match="at least one timed call"):
        timing_summary([], batch_size=4)


def test_ratio_is_ours_over_the_reference_and_absent_without_both_rates():
    assert act_ratio({"chunks_per_s": 3.0}, {"chunks_per_s": 2.0}) == 1.5
    assert act_ratio({"chunks_per_s": 3.0}, {"skipped": "no LeRobot"}) is None
    assert act_ratio({"skipped": "crashed"}, {"chunks_per_s": 2.0}) is None
    assert act_ratio({"chunks_per_s": 3.0}, None) is None


def test_action_agreement_is_relative_to_the_actions_scale():
    assert action_agreement(5e-5, 0.3)["same_actions"]            # scale < 1: absolute 1e-4
    assert not action_agreement(2e-4, 0.3)["same_actions"]
    assert action_agreement(5e-4, 10.0)["same_actions"]           # 1e-4 of 10
    assert not action_agreement(2e-3, 10.0)["same_actions"]
    assert action_agreement(None, None) == {"max_abs_diff": None, "actions_scale": None, "same_actions": None}


def test_final_line_has_the_benchmark_convention():
    results = {"ours": {"chunks_per_s": 4.0}, "reference": {"chunks_per_s": 2.0},
               "actions": action_agreement(0.0, 1.0)}
    line = final_line(results, "cpu (2 cpus)", {"size": "small"})
    assert line["benchmark"] == "vla_rollout"
    assert line["ratios"] == {"vla_act_vs_reference": 2.0}
    assert line["targets"] == {"vla_act_vs_reference": 1.0}
    assert line["device"] == "cpu (2 cpus)" and line["results"] == results
    alone = final_line({"ours": {"chunks_per_s": 4.0}, "reference": {"skipped": "no LeRobot"}}, "cpu", {})
    assert alone["ratios"] == {"vla_act_vs_reference": None}


def test_reference_python_from_the_flag_then_the_environment(tmp_path):
    python = tmp_path / "python"
    python.write_text("")
    other = tmp_path / "other"
    other.write_text("")
    assert resolve_reference_python(str(python), {"INFINIRL_LEROBOT_PYTHON": str(other)}) == (str(python), "")
    assert resolve_reference_python(None, {"INFINIRL_LEROBOT_PYTHON": str(other)}) == (str(other), "")
    none, why = resolve_reference_python(None, {})
    assert none is None and "--reference-python" in why and "our row only" in why
    missing, why = resolve_reference_python(None, {"INFINIRL_LEROBOT_PYTHON": str(tmp_path / "nope")})
    assert missing is None and "$INFINIRL_LEROBOT_PYTHON" in why and "does not exist" in why


def test_sizes_keep_what_lerobot_and_our_loader_need():
    for name, spec in SIZES.items():
        if spec is None:
            continue
        vlm, expert = spec["VLM"], spec["EXPERT"]
        assert vlm["num_heads"] == expert["num_heads"] == 8, name  # LeRobot's joint attention: 8 heads
        assert (vlm["num_kv_heads"], vlm["head_dim"], vlm["depth"]) == (
            expert["num_kv_heads"], expert["head_dim"], expert["depth"]), name
        assert spec["IMAGE_SIZE"] % spec["VISION"]["patch_size"] == 0, name


def test_compare_actions_reads_both_sides_files(tmp_path):
    import torch
    from safetensors.torch import save_file

    assert compare_actions(tmp_path)["same_actions"] is None  # a side did not run
    theirs = torch.tensor([[[0.5, -2.0]]])
    save_file({"actions": theirs}, str(tmp_path / "reference_actions.safetensors"))
    save_file({"actions": theirs + torch.tensor([[[0.0, 1e-3]]])}, str(tmp_path / "ours_actions.safetensors"))
    result = compare_actions(tmp_path)
    assert result["max_abs_diff"] == pytest.approx(1e-3, rel=1e-3) and result["actions_scale"] == 2.0
    assert result["same_actions"] is False
    save_file({"actions": theirs[:, :, :1]}, str(tmp_path / "ours_actions.safetensors"))
    assert compare_actions(tmp_path)["same_actions"] is False  # shapes differ


def test_a_failed_side_or_different_actions_fail_the_run_and_a_missing_reference_does_not():
    rates = {"ours": {"chunks_per_s": 4.0}, "reference": {"chunks_per_s": 2.0}}
    assert run_failures({**rates, "actions": action_agreement(0.0, 1.0)}) == []
    assert run_failures({"ours": {"chunks_per_s": 4.0}, "reference": {"skipped": "no LeRobot"},
                         "actions": action_agreement(None, None)}) == []
    differ = run_failures({**rates, "actions": action_agreement(0.5, 1.0)})
    assert len(differ) == 1 and differ[0].startswith("same work: the two sides' actions differ")
    crashed = {"ours": {"failed": "row ours exited"}, "reference": {"failed": "stopped: the ours side failed"}}
    assert run_failures({**crashed, "actions": action_agreement(None, None)}) == [
        "ours: row ours exited", "reference: stopped: the ours side failed"]
