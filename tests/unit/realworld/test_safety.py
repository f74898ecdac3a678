"""The safety layer with each fault injected: out-of-range and too-fast commands, a silent commander,
a stalled heartbeat. Real robots underneath (the simulated SO-101, the SO-101 driver on the emulated
bus); outcomes are asserted, with generous deadlines, never timings."""

import logging
import time

import numpy as np
import pytest

from infinirl.realworld.driver import RobotSpec, RobotStoppedError, make_robot
from infinirl.realworld.feetech import Register
from infinirl.realworld.feetech_emulator import FeetechBusEmulator
from infinirl.realworld.safety import SafeRobot, SafetyConfig, SafetyFilter
from infinirl.realworld.sim_so101 import SimSO101
from infinirl.realworld.so101 import SO101_JOINT_HIGH, SO101_MAX_JOINT_VELOCITY, so101_spec


def wait_until(predicate, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.01)
    return predicate()


SPEC = so101_spec(kind="test_so101", control_hz=20.0)


def test_out_of_range_and_too_fast_commands_are_clipped_and_recorded():
    safety = SafetyFilter(SPEC, SafetyConfig(velocity_scale=0.5))
    reference = np.zeros(6)
    step = 0.5 * SO101_MAX_JOINT_VELOCITY[0] / 20.0
    command = np.array([10.0, 0.01, -step * 3, np.nan, 0.0, 1.7])
    safe, records = safety(command, reference)
    np.testing.assert_allclose(safe, [step, 0.01, -step, 0.0, 0.0, 1.0])
    kinds = sorted((record.kind, record.index) for record in records)
    assert kinds == [("gripper", 5), ("joint_limit", 0), ("non_finite", 3), ("velocity", 0), ("velocity", 2)]
    # near a limit, the limit wins over the velocity bound
    reference = np.append(SO101_JOINT_HIGH, 0.5)
    safe, _ = safety(reference + 1.0, reference)
    np.testing.assert_allclose(safe[:5], SO101_JOINT_HIGH)


def test_workspace_box_for_end_effector_commands():
    robot_spec = RobotSpec(
        kind="ee_arm", dof=2, control_hz=10.0, control_mode="ee_position", action_low=[-1, -1, 0, 0],
        action_high=[1, 1, 1, 1], joint_low=[-1, -1], joint_high=[1, 1], max_joint_velocity=[1, 1],
        workspace_low=[-0.5, -0.5, 0.0], workspace_high=[0.5, 0.5, 0.5], max_ee_speed=100.0, has_gripper=True)
    safe, records = SafetyFilter(robot_spec)(np.array([0.9, 0.0, -0.2, 0.5]), np.array([0.4, 0.0, 0.1, 0.5]))
    np.testing.assert_allclose(safe, [0.5, 0.0, 0.0, 0.5])
    assert [record.kind for record in records] == ["workspace", "workspace"]


@pytest.fixture
def sim_arm():
    robot = SafeRobot(SimSO101(control_hz=50.0, image_size=None),
                      SafetyConfig(command_deadline_s=0.2, heartbeat_deadline_s=None))
    robot.connect()
    yield robot
    robot.close()


def test_clip_reaches_the_robot_and_is_logged(sim_arm, caplog):
    start = sim_arm.observe().joint_positions
    with caplog.at_level(logging.WARNING, logger="infinirl.realworld.safety"):
        sim_arm.act(np.append(start + np.array([5.0, 0, 0, 0, 0]), 1.0))
    assert sim_arm.clip_counts["velocity"] == 1 and sim_arm.clip_counts["joint_limit"] == 1
    assert any("clipped (velocity)" in message for message in caplog.messages)
    time.sleep(0.3)  # the arm went to the clipped target (0.03 rad), nowhere near the joint limit it was sent
    assert sim_arm.observe().joint_positions[0] - start[0] < 0.2


def test_silent_commander_makes_the_watchdog_hold(sim_arm):
    sim_arm.act(sim_arm.observe().current_target(sim_arm.spec))
    # the watchdog records the event, then holds the driver: wait for both, not the event alone
    assert wait_until(lambda: sim_arm.event_counts["watchdog_hold"] == 1 and sim_arm.driver.mode == "holding")
    assert sim_arm.driver.stats.holds == 1
    sim_arm.act(sim_arm.observe().current_target(sim_arm.spec))  # a command resumes
    assert wait_until(lambda: sim_arm.driver.mode == "running" or sim_arm.event_counts["watchdog_hold"] == 2)


def test_stalled_heartbeat_stops_the_sim_arm():
    robot = SafeRobot(SimSO101(control_hz=50.0, image_size=None),
                      SafetyConfig(command_deadline_s=None, heartbeat_deadline_s=0.2))
    robot.connect()
    try:
        # the monitor records the event, then stops the driver: wait for both, not the event alone
        assert wait_until(lambda: robot.event_counts["heartbeat_stop"] == 1 and robot.driver.mode == "stopped")
        with pytest.raises(RobotStoppedError):
            robot.act(robot.observe().current_target(robot.spec))
        robot.reset()
        assert robot.driver.mode == "running"
        robot.act(robot.observe().current_target(robot.spec))
    finally:
        robot.close()


def test_stalled_heartbeat_turns_the_real_arms_torque_off():
    with FeetechBusEmulator() as emulator:
        robot = SafeRobot(make_robot("so101_feetech", port=emulator.path),
                          SafetyConfig(command_deadline_s=None, heartbeat_deadline_s=0.3))
        robot.connect()
        try:
            torque = lambda: [emulator.register(i, Register.TORQUE_ENABLE) for i in range(1, 7)]  # noqa: E731
            assert wait_until(lambda: torque() == [1] * 6)
            for _ in range(5):  # a live pipeline keeps the arm on
                robot.heartbeat()
                time.sleep(0.02)
            assert wait_until(lambda: robot.event_counts["heartbeat_stop"] == 1)
            assert wait_until(lambda: torque() == [0] * 6)
        finally:
            robot.close()


def test_act_returns_the_command_it_sent():
    robot = SafeRobot(SimSO101(control_hz=20.0), SafetyConfig(command_deadline_s=None, heartbeat_deadline_s=None))
    robot.connect()
    try:
        reference = robot.observe().current_target(robot.spec)
        sent = robot.act(np.append(np.full(5, SO101_JOINT_HIGH.max() * 10), 1.0))
        assert robot.clip_counts["velocity"] > 0
        assert np.all(np.abs(sent - reference)[:5] <= robot.filter._max_step + 1e-9)
    finally:
        robot.close()


def test_a_command_deadline_within_one_control_period_is_refused():
    from infinirl.config import ConfigError, to_dataclass
    from infinirl.runners.realworld_sac_config import RealWorldSACConfig

    def config(deadline_s):
        return to_dataclass(RealWorldSACConfig, {"robot": {"kind": "sim_so101", "options": {"control_hz": 20.0},
                                                           "command_deadline_s": deadline_s}})

    with pytest.raises(ConfigError, match=r"robot.command_deadline_s=0.05 .*robot.options.control_hz") as error:
        config(0.05)
    assert "\n" not in str(error.value)
    config(0.06)


@pytest.mark.parametrize("runner", ["realworld_sac", "hg_dagger"])
def test_a_new_velocity_scale_resumes_only_where_actions_are_absolute_targets(runner, tmp_path):
    """With task.action_mode=delta an action is a step of velocity_scale times the top speed per
    period: the policy (and the replay's actions) learned at the old scale, so a new one on resume
    is refused with the reason; with absolute targets it only limits speed, and takes effect."""
    from infinirl.config import ConfigError, to_dataclass, to_plain
    from infinirl.runners.hg_dagger_config import HGDAggerConfig
    from infinirl.runners.loop import RunLoop
    from infinirl.runners.realworld_sac_config import RealWorldSACConfig

    cls = {"realworld_sac": RealWorldSACConfig, "hg_dagger": HGDAggerConfig}[runner]

    def config(scale, mode, fleet_mode=None):
        raw = {"output_dir": str(tmp_path / "run"), "robot": {"velocity_scale": scale},
               "task": {"action_mode": mode}}
        if runner == "hg_dagger":
            raw["dagger"] = {"initial_demos": 0}  # scripted demos need delta actions
        if fleet_mode is not None:
            raw["robot"]["fleet"] = [{"kind": "sim_sawyer"},
                                     {"kind": "sim_sawyer", "task": {"action_mode": fleet_mode}}]
            raw["placement"] = {"robot": "0-1"}
        return to_dataclass(cls, raw)

    with pytest.raises(ConfigError, match=r"robot.velocity_scale: 0.5 -> 0.3.*task.action_mode=delta"):
        RunLoop(config(0.3, "delta"))._check_config("ckpt", to_plain(config(0.5, "delta")), 2)
    loop = RunLoop(config(0.3, "absolute"))
    loop._check_config("ckpt", to_plain(config(0.5, "absolute")), 2)
    assert loop._history_record["changes"] == {"robot.velocity_scale": {"old": 0.5, "new": 0.3}}
    if runner == "realworld_sac":  # one robot of the fleet acting in deltas is enough to refuse it
        with pytest.raises(ConfigError, match=r"robot.velocity_scale: 0.5 -> 0.3"):
            RunLoop(config(0.3, "absolute", "delta"))._check_config(
                "ckpt", to_plain(config(0.5, "absolute", "delta")), 2)
