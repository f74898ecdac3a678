"""Online scaling's pure parts: the busy-ratio policy's hysteresis, the command file, resized specs."""

import json

import pytest

from infinirl.runtime.placement import PlacementError, parse_spec, resized_spec
from infinirl.runtime.scaling import BusyRatioPolicy, ScaleCommands, ScalingConfig, parse_scale_command


def policy(**kw):
    return BusyRatioPolicy(ScalingConfig(**{"grow_above": 0.8, "shrink_below": 0.3, "patience": 2,
                                            "min_ranks": 1, "max_ranks": 3, **kw}))


def run(p, ranks, ratios):
    out = []
    for ratio in ratios:
        ranks = p.decide(ranks, ratio)
        out.append(ranks)
    return out


def test_grows_only_after_patience_busy_iterations_in_a_row():
    assert run(policy(), 1, [0.9, 0.5, 0.9, 0.95, 0.9, 0.9]) == [1, 1, 1, 2, 2, 3]


def test_shrinks_only_after_patience_idle_iterations_and_stays_within_bounds():
    assert run(policy(), 3, [0.1, 0.1, 0.1, 0.1, 0.1, 0.1]) == [3, 2, 2, 1, 1, 1]
    assert run(policy(), 3, [0.9] * 4) == [3, 3, 3, 3]  # already at max_ranks


def test_a_ratio_inside_the_band_never_changes_anything():
    assert run(policy(), 2, [0.5, 0.79, 0.31, 0.6] * 3) == [2] * 12


def test_a_ratio_flapping_across_one_threshold_does_not_flap_the_ranks():
    assert run(policy(), 2, [0.85, 0.75] * 6) == [2] * 12


def resizes_of_a_run(p, eta, iterations, busy_ratio_with):
    """The resizes an asynchronous run makes: ``take(k)`` submits up to trajectory ``k + eta`` on
    the env layout of that moment, so after a resize at ``k`` the trajectories ``k + 1 .. k + eta``
    still come from the old layout, and report its rank count with its busy ratio."""
    ranks, collected_with, resizes = 1, {}, []
    for k in range(iterations):
        for j in range(k, k + eta + 1):
            collected_with.setdefault(j, ranks)
        measured = collected_with.pop(k)
        wanted = p.decide(ranks, busy_ratio_with[measured], measured_ranks=measured)
        if wanted != ranks:
            resizes.append((k, ranks, wanted))
            ranks = wanted
    return resizes


def test_ratios_measured_on_the_layout_before_a_resize_decide_nothing():
    """eta=2, patience=1: the env is the bottleneck with one rank and busy half the time with two.
    One resize, not a second one on the two trajectories collected ahead on one rank."""
    assert resizes_of_a_run(policy(patience=1), eta=2, iterations=8, busy_ratio_with={1: 0.95, 2: 0.5}) == [
        (0, 1, 2)]


def test_a_ratio_of_the_current_layout_counts_as_before():
    assert run(policy(), 1, [0.9, 0.9]) == [1, 2]
    p = policy()
    assert [p.decide(1, 0.9, measured_ranks=1), p.decide(1, 0.9, measured_ranks=1)] == [1, 2]


@pytest.mark.parametrize("kw, key", [({"grow_above": 0.3, "shrink_below": 0.3}, "shrink_below"),
                                     ({"min_ranks": 3, "max_ranks": 2}, "min_ranks"),
                                     ({"patience": 0}, "patience")])
def test_contradicting_settings_name_the_key(kw, key):
    with pytest.raises(ValueError, match=f"scaling.{key}"):
        ScalingConfig(**kw).check()


def test_parse_scale_command_names_the_file_and_the_problem():
    assert parse_scale_command('{"env": 2}', ["env"], "f") == {"env": 2}
    for text, match in [("{env: 2}", "not JSON"), ("[2]", "object"), ('{"actor": 2}', "'actor' cannot be scaled"),
                        ('{"env": 0}', "whole number"), ('{"env": true}', "whole number")]:
        with pytest.raises(ValueError, match=match) as info:
            parse_scale_command(text, ["env"], "o/scale.json")
        assert str(info.value).startswith("o/scale.json: ")


def test_a_command_is_read_once_and_set_aside(tmp_path, capsys):
    path = tmp_path / "scale.json"
    commands = ScaleCommands(str(path), ["env"])
    assert commands.poll() == {}
    path.write_text(json.dumps({"env": 2}))
    assert commands.poll() == {"env": 2}
    assert not path.exists() and (tmp_path / "scale.json.applied").exists()
    assert commands.poll() == {}
    path.write_text('{"env": -1}')
    assert commands.poll() == {}
    assert (tmp_path / "scale.json.rejected").exists()
    assert "scaling command rejected" in capsys.readouterr().out


@pytest.mark.parametrize("spec, n, expected", [("0", 2, "0:0-1"), ("0", 1, "0:0"), ("0-1:0-3", 2, "0-1:0-1"),
                                               ("node:1", 3, "node:1:0-2"), ("all", 4, "all:0-3"),
                                               ("0,2,3", 6, "0,2-3:0-5")])
def test_resized_spec_keeps_the_resources_and_sets_the_rank_count(spec, n, expected):
    resized = resized_spec(spec, n)
    assert resized == expected
    assert parse_spec(resized).num_processes == n
    assert parse_spec(resized).indices == parse_spec(spec).indices


def test_robot_placements_and_zero_ranks_cannot_be_resized():
    with pytest.raises(PlacementError, match="robot"):
        resized_spec("robot:0", 2, "arm")
    with pytest.raises(PlacementError, match="at least 1"):
        resized_spec("0", 0, "env")
