"""Intervention devices down to their wire formats: keys typed into a real pseudo-terminal, joystick
records (``struct js_event``) written into a pipe, and the simulated human's take-over rule."""

import errno
import os
import pty
import termios
from types import SimpleNamespace

import numpy as np
import pytest

from infinirl.realworld.intervention import INTERVENTION_DEVICES, HumanInput, fd_reader
from infinirl.realworld.intervention.gamepad import JS_EVENT_AXIS, JS_EVENT_BUTTON, JS_EVENT_INIT, js_event
from infinirl.realworld.intervention.simulated_human import action_distance


def test_builtin_devices_are_registered():
    assert {"keyboard", "gamepad", "simulated_human"} <= set(INTERVENTION_DEVICES.names())


# ---------------------------------------------------------------- keyboard
@pytest.fixture
def terminal():
    """A pseudo-terminal: the device reads the follower side, the test types into the leader."""
    leader, follower = pty.openpty()
    yield leader, follower
    os.close(leader)
    os.close(follower)


def test_keyboard_takes_over_steers_marks_and_hands_back(terminal):
    leader, follower = terminal
    before = termios.tcgetattr(follower)
    device = INTERVENTION_DEVICES.get("keyboard")(action_dim=4, fd=follower, rest=[0, 0, 0, 1], latched_axes=[3])
    assert termios.tcgetattr(follower)[3] & termios.ICANON == 0  # raw: keys arrive one by one
    assert device.poll() == HumanInput(active=False)  # nothing typed: never blocks
    os.write(leader, b"d")  # steering before a take-over moves nothing
    assert not device.poll().active
    os.write(leader, b" dde")  # take over, +2 steps on entry 0 (clipped to 1), + on entry 2
    given = device.poll()
    assert given.active and np.allclose(given.action, [1, 0, 1, 1])
    given = device.poll()  # no key this step: momentary entries rest, the latched gripper holds
    assert given.active and np.allclose(given.action, [0, 0, 0, 1])
    os.write(leader, b"jjx")  # gripper closes (latched), entry 1 minus
    assert np.allclose(device.poll().action, [0, -1, 0, -1])
    assert np.allclose(device.poll().action, [0, 0, 0, -1])
    os.write(leader, b"s ")  # success mark, then hand back
    given = device.poll()
    assert given.marks == ("success",) and not given.active
    os.write(leader, b"f")
    assert device.poll().marks == ("failure",)
    device.close()
    assert termios.tcgetattr(follower) == before  # the terminal's settings are restored


def test_keyboard_releases_control_when_the_terminal_goes_away():
    leader, follower = pty.openpty()
    try:
        device = INTERVENTION_DEVICES.get("keyboard")(action_dim=2, fd=follower, latched_axes=[1])
        os.write(leader, b" l")
        assert device.poll().active
        os.close(leader)  # the terminal window closes: the follower reads EIO from now on
        leader = None
        assert device.poll() == HumanInput(active=False) and device.reader.eof
        assert device.poll() == HumanInput(active=False)  # for good, without reading again
        device.close()
    finally:
        if leader is not None:
            os.close(leader)
        os.close(follower)


def test_keyboard_held_off_gives_control_back_and_refuses_the_toggle(terminal, caplog):
    leader, follower = terminal
    device = INTERVENTION_DEVICES.get("keyboard")(action_dim=2, fd=follower)
    os.write(leader, b" d")
    assert device.poll().active
    device.hold_off("evaluation")
    assert not device.active and "evaluation episode is running" in caplog.text  # given back, and said so
    os.write(leader, b" ds")  # a take-over during the evaluation: refused; the mark still arrives
    assert device.poll() == HumanInput(active=False, marks=("success",))
    assert "take-over refused" in caplog.text and "until the next training episode" in caplog.text
    device.hold_off(None)
    assert not device.poll().active  # the refused toggle does not take over later
    os.write(leader, b" ")
    assert device.poll().active
    device.close()


def test_keyboard_refuses_a_key_bound_twice(terminal):
    with pytest.raises(ValueError, match="bound twice"):
        INTERVENTION_DEVICES.get("keyboard")(action_dim=2, fd=terminal[1], axis_keys=["as", "jl"])


# ---------------------------------------------------------------- gamepad
@pytest.fixture
def joystick():
    """A pipe standing in for /dev/input/jsN: the test writes js_event records, the device reads them."""
    read_end, write_end = os.pipe()
    yield read_end, write_end
    os.close(read_end)
    os.close(write_end)


def test_js_event_is_the_kernel_record():
    record = js_event(time_ms=0x01020304, value=-2, type=JS_EVENT_AXIS, number=3)
    assert record == bytes([0x04, 0x03, 0x02, 0x01, 0xFE, 0xFF, 0x02, 0x03])  # u32 LE, s16 LE, u8, u8


def test_gamepad_holds_control_while_the_button_is_down(joystick):
    read_end, write_end = joystick
    device = INTERVENTION_DEVICES.get("gamepad")(action_dim=3, fd=read_end, axes=[0, 1], invert=[1], deadzone=0.1,
                                                 takeover_button=5, success_button=0, failure_button=1,
                                                 rest=[0, 0, 1])
    # On open the driver reports the initial state: synthetic events (JS_EVENT_INIT), not presses.
    os.write(write_end, js_event(time_ms=1, value=1, type=JS_EVENT_BUTTON | JS_EVENT_INIT, number=0)
             + js_event(time_ms=1, value=16384, type=JS_EVENT_AXIS | JS_EVENT_INIT, number=0))
    assert device.poll() == HumanInput(active=False)
    os.write(write_end, js_event(time_ms=2, value=1, type=JS_EVENT_BUTTON, number=5)
             + js_event(time_ms=3, value=-32767, type=JS_EVENT_AXIS, number=1)
             + js_event(time_ms=4, value=2000, type=JS_EVENT_AXIS, number=2))  # an unmapped axis
    given = device.poll()
    assert given.active and np.allclose(given.action, [16384 / 32767, 1.0, 1.0])
    record = js_event(time_ms=5, value=1000, type=JS_EVENT_AXIS, number=0)  # inside the deadzone
    os.write(write_end, record[:5])  # a partial record waits for the rest of its bytes
    assert np.allclose(device.poll().action, [16384 / 32767, 1.0, 1.0])
    os.write(write_end, record[5:] + js_event(time_ms=6, value=0, type=JS_EVENT_BUTTON, number=0)
             + js_event(time_ms=7, value=1, type=JS_EVENT_BUTTON, number=0))  # release, then a real press
    given = device.poll()
    assert np.allclose(given.action, [0.0, 1.0, 1.0]) and given.marks == ("success",)
    os.write(write_end, js_event(time_ms=8, value=0, type=JS_EVENT_BUTTON, number=5)
             + js_event(time_ms=9, value=1, type=JS_EVENT_BUTTON, number=1))
    given = device.poll()
    assert not given.active and given.marks == ("failure",)
    device.close()


def test_gamepad_toggle_mode(joystick):
    read_end, write_end = joystick
    device = INTERVENTION_DEVICES.get("gamepad")(action_dim=1, fd=read_end, takeover_button=2, takeover_toggle=True)
    press = js_event(time_ms=1, value=1, type=JS_EVENT_BUTTON, number=2)
    release = js_event(time_ms=2, value=0, type=JS_EVENT_BUTTON, number=2)
    os.write(write_end, press + release)
    assert device.poll().active and device.poll().active  # stays on after the release
    os.write(write_end, press + release)
    assert not device.poll().active


def test_gamepad_held_off_refuses_the_take_over_button(joystick, caplog):
    read_end, write_end = joystick
    toggle = INTERVENTION_DEVICES.get("gamepad")(action_dim=1, fd=read_end, takeover_button=2, takeover_toggle=True)
    press = js_event(time_ms=1, value=1, type=JS_EVENT_BUTTON, number=2)
    release = js_event(time_ms=2, value=0, type=JS_EVENT_BUTTON, number=2)
    os.write(write_end, press + release)
    assert toggle.poll().active
    toggle.hold_off("evaluation")  # a toggled take-over goes back to the policy
    assert not toggle.poll().active
    os.write(write_end, press + release)  # refused: it toggles nothing, now or later
    assert not toggle.poll().active and "take-over refused" in caplog.text
    toggle.hold_off(None)
    assert not toggle.poll().active
    os.write(write_end, press + release)
    assert toggle.poll().active

    dead_man = INTERVENTION_DEVICES.get("gamepad")(action_dim=1, fd=read_end, takeover_button=5)
    dead_man.hold_off("demonstration")
    os.write(write_end, js_event(time_ms=3, value=1, type=JS_EVENT_BUTTON, number=5))
    assert not dead_man.poll().active and not dead_man.poll().active  # held down, steering nothing
    dead_man.hold_off(None)
    assert dead_man.poll().active  # still held when training goes on: control, as the button says


def test_gamepad_releases_control_when_the_pipe_closes():
    read_end, write_end = os.pipe()
    device = INTERVENTION_DEVICES.get("gamepad")(action_dim=1, fd=read_end, takeover_button=5)
    os.write(write_end, js_event(time_ms=1, value=1, type=JS_EVENT_BUTTON, number=5)
             + js_event(time_ms=2, value=30000, type=JS_EVENT_AXIS, number=0))
    assert device.poll().active
    os.close(write_end)  # the writer goes away: EOF
    given = device.poll()
    assert given == HumanInput(active=False) and device.reader.eof
    assert not device.buttons and not device.axis_values and not device.poll().active
    device.close()
    os.close(read_end)


@pytest.mark.parametrize("errno_", [errno.ENODEV, errno.EBADF])
def test_gamepad_unplugged_releases_control_instead_of_raising(joystick, monkeypatch, errno_):
    """An unplugged joystick reads ENODEV; any other read error also counts as the pad being gone."""
    read_end, write_end = joystick
    device = INTERVENTION_DEVICES.get("gamepad")(action_dim=1, fd=read_end, takeover_button=5,
                                                 takeover_toggle=True)
    os.write(write_end, js_event(time_ms=1, value=1, type=JS_EVENT_BUTTON, number=5))
    assert device.poll().active

    def unplugged(fd, size):
        raise OSError(errno_, os.strerror(errno_))

    monkeypatch.setattr(fd_reader.os, "read", unplugged)
    assert device.poll() == HumanInput(active=False) and device.reader.eof and not device.toggled
    assert device.poll() == HumanInput(active=False)
    monkeypatch.undo()
    device.close()


def test_gamepad_names_a_missing_device(tmp_path):
    with pytest.raises(OSError, match="gamepad: cannot open .*js9.*path option"):
        INTERVENTION_DEVICES.get("gamepad")(action_dim=2, path=str(tmp_path / "js9"))


# ---------------------------------------------------------------- simulated human
def test_action_distance_ignores_padded_entries():
    assert action_distance(np.array([1.0, 1.0, 5.0]), np.array([1.0, 0.0])) == pytest.approx(1.0)


def expert_towards_zero(observation):
    return np.array([-observation["state"][0], 0.0], np.float32)


def test_simulated_human_takes_over_after_the_reaction_delay_and_hands_back():
    human = INTERVENTION_DEVICES.get("simulated_human")(action_dim=2, expert=expert_towards_zero, threshold=0.5,
                                                        reaction_steps=2, correct_steps=3)
    obs = {"state": np.array([0.5], np.float32)}  # the expert wants [-0.5, 0]
    good, bad = np.array([-0.5, 0.0]), np.array([0.5, 0.0])
    assert not human.poll(observation=obs, policy_action=good).active
    seen = [human.poll(observation=obs, policy_action=bad).active for _ in range(3)]
    assert seen == [False, False, True]  # the policy acts through 2 drifting steps, then the human
    given = human.poll(observation=obs, policy_action=bad)
    assert given.active and np.allclose(given.action, [-0.5, 0.0])
    assert human.poll(observation=obs, policy_action=good).active  # 3 corrective steps in all
    assert not human.poll(observation=obs, policy_action=good).active  # handed back
    assert human.takeovers == 1
    human.reset()
    assert [human.poll(observation=obs, policy_action=bad).active for _ in range(2)] == [False, False]
    assert not human.poll(observation=obs, policy_action=None).active  # no proposal: nothing to judge


def test_simulated_human_marks_from_the_env_success_signal_once_per_episode():
    env = SimpleNamespace(last_observation=SimpleNamespace(info={"success": False}))
    human = INTERVENTION_DEVICES.get("simulated_human")(action_dim=1, expert=lambda o: np.zeros(1), give_up_steps=3)
    human.bind(env)
    assert human.poll().marks == ()
    env.last_observation.info["success"] = True
    assert human.poll().marks == ("success",)
    assert human.poll().marks == ()  # once per episode
    human.reset()
    env.last_observation.info["success"] = False
    assert [human.poll().marks for _ in range(4)] == [(), (), (), ("failure",)]  # gives up after 3 steps


def test_simulated_human_held_off_neither_takes_over_nor_marks():
    env = SimpleNamespace(last_observation=SimpleNamespace(info={"success": True}))
    human = INTERVENTION_DEVICES.get("simulated_human")(action_dim=2, expert=expert_towards_zero, reaction_steps=0,
                                                        reaction_jitter=3)
    human.bind(env)
    obs, bad = {"state": np.array([0.5], np.float32)}, np.array([0.5, 0.0])
    human.hold_off("evaluation")
    assert [human.poll(observation=obs, policy_action=bad) for _ in range(5)] == [HumanInput(active=False)] * 5
    assert (human.takeovers, human.steps, human.drifting) == (0, 0, 0)  # its state and draws as they were
    human.hold_off(None)
    assert human.poll(observation=obs, policy_action=bad).marks == ("success",)


def test_simulated_human_with_a_named_expert_needs_the_env():
    human = INTERVENTION_DEVICES.get("simulated_human")(action_dim=4)
    with pytest.raises(RuntimeError, match="bind"):
        human.poll(observation={"state": np.zeros(3)}, policy_action=np.zeros(4))


def test_simulated_human_reaction_jitter_is_seeded():
    def delays(seed):
        human = INTERVENTION_DEVICES.get("simulated_human")(action_dim=1, expert=lambda o: np.zeros(1),
                                                            reaction_jitter=3, seed=seed)
        out = []
        for _ in range(5):
            human.reset()
            out.append(human.delay)
        return out

    assert delays(1) == delays(1) and all(2 <= d <= 5 for d in delays(1))
    assert delays(1) != delays(2)


def test_intervention_spec_builds_by_name_and_refuses_unknown_names():
    from infinirl.realworld.intervention.spec import InterventionSpec

    spec = InterventionSpec(device="simulated_human", options={"threshold": 0.25, "expert": expert_towards_zero})
    device = spec.build(action_dim=2)
    assert device.threshold == 0.25 and device.action_dim == 2
    with pytest.raises(KeyError, match="joystick"):
        InterventionSpec(device="joystick")
    with pytest.raises(ValueError, match="reward"):
        InterventionSpec(device="keyboard", reward="crowd")
