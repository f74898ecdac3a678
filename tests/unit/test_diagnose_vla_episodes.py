"""scripts/diagnose_vla_episodes.py: how much a policy's hand follows the task's object (slopes of
its position on the object's), and its one-line refusals of what it cannot diagnose."""

import json
import os
import sys

import numpy as np
import pytest

SCRIPTS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "scripts")
sys.path.insert(0, SCRIPTS)

from diagnose_vla_episodes import follow_slopes, main, ridge_r2  # noqa: E402


def rows(objects, hands):
    return [{"object_start": list(o), "hand": list(h)} for o, h in zip(objects, hands)]


def test_the_slope_is_one_where_the_hand_goes_to_the_object_and_zero_where_it_ignores_it():
    objects = [(-0.1, 0.8, 0.3), (0.0, 0.85, 0.3), (0.1, 0.9, 0.3), (0.05, 0.82, 0.3)]
    follows = [(x + 0.02, y - 0.04, 0.25) for x, y, _ in objects]
    ignores = [(0.045, 0.87, 0.25)] * 4
    half = [(0.5 * x, 0.87, 0.25) for x, _, _ in objects]
    assert follow_slopes(rows(objects, follows)) == pytest.approx([1.0, 1.0])
    assert follow_slopes(rows(objects, ignores)) == pytest.approx([0.0, 0.0])
    assert follow_slopes(rows(objects, half)) == pytest.approx([0.5, 0.0])


def test_the_ridge_probe_reads_a_linear_target_and_not_noise():
    rng = np.random.default_rng(0)
    features = rng.normal(size=(200, 50))
    readable = features[:, :2] @ np.array([[1.0, 0.5], [-0.3, 2.0]])
    noise = rng.normal(size=(200, 2))
    assert min(ridge_r2(features, readable, penalty=1e-3)) > 0.99
    assert max(ridge_r2(features, noise, penalty=1e-3)) < 0.2
    with pytest.raises(ValueError, match="at least 8 rows"):
        ridge_r2(features[:5], readable[:5])


def test_what_it_cannot_diagnose_is_one_line(tmp_path):
    with pytest.raises(SystemExit, match=r"config.json not found: give the output_dir of an embodied run"):
        main([str(tmp_path), "--task", "reach-v3"])
    (tmp_path / "config.json").write_text(json.dumps({"runner": "reasoning", "env": {"name": "gym:Pendulum-v1"}}))
    with pytest.raises(SystemExit, match=r"is not an embodied MetaWorld run \(runner 'reasoning'"):
        main([str(tmp_path), "--task", "reach-v3"])
    (tmp_path / "config.json").write_text(json.dumps({"runner": "embodied", "env": {"name": "metaworld:reach-v3"}}))
    with pytest.raises(SystemExit, match=r"--task 'push-v3' is not one of the run's tasks \['reach-v3'\]"):
        main([str(tmp_path), "--task", "push-v3"])
    with pytest.raises(SystemExit, match=r"--at-step 0: at least 1"):
        main([str(tmp_path), "--task", "reach-v3", "--at-step", "0"])
    with pytest.raises(SystemExit, match=r"--probe 4: at least 8 layouts"):
        main([str(tmp_path), "--task", "reach-v3", "--probe", "4"])
    with pytest.raises(SystemExit, match=r"--episodes 1: at least 2"):
        main([str(tmp_path), "--task", "reach-v3", "--episodes", "1"])
