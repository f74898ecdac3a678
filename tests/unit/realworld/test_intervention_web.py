"""The intervention web page's device: its HTTP API sets what poll() returns (take-over, the human's
action, hand-back, marks delivered once), refuses bad input with a 400 that says what to send and a
missing token with a 403, serves the latest frame as JPEG, and stops cleanly."""

import io
import json
import socket
import urllib.error
import urllib.request

import numpy as np
import pytest
from PIL import Image

from infinirl.realworld.intervention import INTERVENTION_DEVICES
from infinirl.realworld.intervention.web import (
    StaleSession,
    WebControlState,
    WebInterventionDevice,
    parse_action,
    parse_mark,
)

TOKEN = "t0ken/with?odd&chars"


def call(device, path, body=None, *, token=TOKEN, method=None, raw=None, headers=None):
    """(status, parsed JSON or bytes) of one request to the device's API (a POST as JSON, as the page sends it)."""
    query = "" if token is None else ("&" if "?" in path else "?") + "token=" + urllib.request.quote(token, safe="")
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    method = method or ("GET" if data is None else "POST")
    headers = {**({"Content-Type": "application/json"} if method == "POST" else {}), **(headers or {})}
    request = urllib.request.Request(f"http://127.0.0.1:{device.port}{path}{query}", data=data,
                                     method=method, headers=headers)
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            status, content, kind = response.status, response.read(), response.headers.get_content_type()
    except urllib.error.HTTPError as error:
        status, content, kind = error.code, error.read(), error.headers.get_content_type()
    return status, json.loads(content) if kind == "application/json" else content


@pytest.fixture
def device():
    with WebInterventionDevice(action_dim=3, token=TOKEN, axis_labels=["x", "y", "grip"]) as dev:
        yield dev


def test_the_registry_builds_it_and_its_url_carries_the_token():
    dev = INTERVENTION_DEVICES.get("web")(action_dim=2, token="abc")
    try:
        assert isinstance(dev, WebInterventionDevice) and dev.port > 0
        assert dev.url == f"http://127.0.0.1:{dev.port}/?token=abc"
        status, page = call(dev, "/", token="abc")
        assert status == 200 and b"<title>InfiniRL intervention</title>" in page
    finally:
        dev.close()


def test_on_every_interface_the_url_names_this_node():
    with WebInterventionDevice(action_dim=2, host="0.0.0.0", token="a b") as dev:
        assert dev.url == f"http://{socket.gethostname()}:{dev.port}/?token=a%20b"
        assert call(dev, "/api/state", token="a b")[0] == 200


def test_take_over_act_and_hand_back_set_what_poll_returns(device):
    assert device.poll().active is False
    status, state = call(device, "/api/takeover", {})
    assert status == 200 and state["active"] is True and state["actor"] == "human"
    session = state["session"]
    human = device.poll(policy_action=np.array([0.5, 0.5, 0.5]))
    assert human.active and np.array_equal(human.action, [0.0, 0.0, 0.0])  # a centred joystick

    assert call(device, "/api/action", {"session": session, "action": [0.25, -1, 1.0]}) == (200, {"ok": True})
    human = device.poll()
    np.testing.assert_array_equal(human.action, [0.25, -1.0, 1.0])
    human.action[0] = 9.0  # the caller's copy: the device's action stays as the page set it
    np.testing.assert_array_equal(device.poll().action, [0.25, -1.0, 1.0])

    status, state = call(device, "/api/state")
    assert state["policy_action"] == [0.5, 0.5, 0.5] and state["polls"] == 4
    assert state["axis_labels"] == ["x", "y", "grip"] and state["pad_axes"] == [0, 1]
    assert "session" not in state  # only the page that took over learns its id

    status, state = call(device, "/api/handback", {"session": session})
    assert status == 200 and state["active"] is False and state["released_by"] == "hand-back"
    assert device.poll().active is False and device.poll().action is None
    assert state["action"] == [0.0, 0.0, 0.0]  # the last take-over's action is gone

    # Taking over with the page's present action starts from it (a slider the human already moved).
    call(device, "/api/takeover", {"action": [0, 0, -0.5]})
    np.testing.assert_array_equal(device.poll().action, [0.0, 0.0, -0.5])
    assert (device.stats.takeovers, device.stats.handbacks) == (2, 1)


def test_only_the_page_holding_the_latest_take_over_steers_or_hands_back(device):
    first = call(device, "/api/takeover", {"action": [0.5, 0.5, 0.5]})[1]["session"]
    second = call(device, "/api/takeover", {})[1]["session"]  # another page takes over
    assert first != second
    np.testing.assert_array_equal(device.poll().action, [0, 0, 0])  # not the first page's action
    for path, body in (("/api/action", {"session": first, "action": [1, 1, 1]}), ("/api/handback", {"session": first}),
                       ("/api/action", {"session": "made-up", "action": [1, 1, 1]})):
        status, answer = call(device, path, body)
        assert status == 409 and "take over again" in answer["error"]
    human = device.poll()
    assert human.active and np.array_equal(human.action, [0, 0, 0])
    status, answer = call(device, "/api/action", {"action": [1, 1, 1]})
    assert status == 400 and "'session'" in answer["error"]
    assert call(device, "/api/action", {"session": second, "action": [0, 1, 0]})[0] == 200
    np.testing.assert_array_equal(device.poll().action, [0, 1, 0])
    assert call(device, "/api/handback", {"session": second})[0] == 200
    assert call(device, "/api/handback", {"session": second})[0] == 409  # that session has ended
    assert call(device, "/api/action", {"session": second, "action": [1, 1, 1]})[0] == 409
    assert device.poll().active is False
    assert (device.stats.stale_requests, device.stats.rejected_requests, device.stats.handbacks) == (5, 1, 1)


def test_during_an_evaluation_a_take_over_is_refused_with_the_reason_and_when_control_opens(device):
    """Evaluation episodes measure the policy alone: the control loop holds the device off, and the
    page says so instead of accepting a take-over that would steer nothing (or corrupt the metric)."""
    session = call(device, "/api/takeover", {"action": [0.5, 0, 0]})[1]["session"]
    device.hold_off("evaluation")  # the control loop starts an evaluation episode
    assert device.held_off == "evaluation" and device.poll().active is False  # the held take-over is given back
    status, state = call(device, "/api/state")
    assert state["held_off"] == "evaluation" and state["released_by"] == "evaluation" and not state["active"]
    assert "evaluation episode is running" in state["held_off_message"]

    status, answer = call(device, "/api/takeover", {})
    assert status == 409 and answer["held_off"] == "evaluation"
    assert "evaluation episode is running" in answer["error"] and "until the next training episode" in answer["error"]
    status, answer = call(device, "/api/action", {"session": session, "action": [1, 1, 1]})
    assert status == 409 and "evaluation episode is running" in answer["error"]  # the released page learns why
    assert device.poll().active is False and device.stats.refused_takeovers == 1
    assert call(device, "/api/mark", {"mark": "success"})[0] == 200  # still taken: it may judge the episode that ended
    assert device.poll().marks == ("success",)

    device.hold_off(None)  # the next training episode starts
    status, state = call(device, "/api/takeover", {})
    assert status == 200 and state["held_off"] is None and state["held_off_message"] is None
    assert device.poll().active
    assert (device.stats.takeovers, device.stats.refused_takeovers) == (2, 1)


def test_posts_must_be_json_from_this_server_s_own_pages():
    """Without a token, another site's page open in a browser here must not be able to take over."""
    with WebInterventionDevice(action_dim=2, allow_no_token=True) as dev:
        host = f"127.0.0.1:{dev.port}"
        for headers in ({"Content-Type": "text/plain"}, {"Content-Type": "application/x-www-form-urlencoded"}):
            status, answer = call(dev, "/api/takeover", {}, token=None, headers=headers)
            assert status == 415 and "application/json" in answer["error"]
        for origin in ("http://evil.example", "null", f"http://{host}.evil.example", "file://"):
            status, answer = call(dev, "/api/takeover", {}, token=None, headers={"Origin": origin})
            assert status == 403 and "another site" in answer["error"]
        assert dev.poll().active is False and dev.stats.rejected_requests == 6
        assert call(dev, "/api/state", token=None, headers={"Origin": "http://evil.example"})[0] == 200  # a read
        status, state = call(dev, "/api/takeover", {}, token=None, headers={"Origin": f"http://{host}"})
        assert status == 200 and dev.poll().active
        assert call(dev, "/api/handback", {"session": state["session"]}, token=None)[0] == 200  # no Origin: not a page


def test_marks_are_delivered_once_in_order(device):
    for mark in ("failure", "success"):
        assert call(device, "/api/mark", {"mark": mark})[0] == 200
    assert call(device, "/api/state")[1]["marks_pending"] == ["failure", "success"]
    first = device.poll()
    assert first.marks == ("failure", "success") and first.active is False
    assert device.poll().marks == ()
    assert call(device, "/api/state")[1]["marks_pending"] == []


@pytest.mark.parametrize(("path", "body", "message"), [
    ("/api/action", b"not json", "must be a JSON object"),
    ("/api/action", b"[1, 2, 3]", "must be a JSON object, got list"),
    ("/api/action", b"{}", "needs 'action'"),
    ("/api/action", b'{"action": [0, 0]}', "list of 3 numbers"),
    ("/api/action", b'{"action": [0, 0, 1.5]}', "within [-1, 1]"),
    ("/api/action", b'{"action": [0, 0, NaN]}', "finite"),
    ("/api/action", b'{"action": [0, true, 0]}', "must be numbers"),
    ("/api/action", b'{"action": [0, "1", 0]}', "must be numbers"),
    ("/api/takeover", b'{"action": [2, 0, 0]}', "within [-1, 1]"),
    ("/api/mark", b'{"mark": "win"}', "one of ['success', 'failure']"),
    ("/api/mark", b"{}", "one of ['success', 'failure']"),
])
def test_bad_input_is_a_400_that_says_what_to_send_and_changes_nothing(device, path, body, message):
    status, answer = call(device, path, raw=body)
    assert status == 400 and message in answer["error"]
    human = device.poll()
    assert human.active is False and human.marks == ()
    assert device.stats.rejected_requests == 1


@pytest.mark.parametrize("token", [None, "wrong", TOKEN + "x", ""])
def test_a_missing_or_wrong_token_is_refused_with_403(device, token):
    for path, body in (("/", None), ("/api/state", None), ("/api/takeover", {}), ("/api/frame/front", None)):
        status, answer = call(device, path, body, token=token)
        assert status == 403 and "token" in answer["error"]
    assert device.poll().active is False


def test_the_latest_frame_is_served_as_jpeg(device):
    assert call(device, "/api/frame/front")[0] == 404  # nothing shown yet
    rows = np.linspace(0, 255, 48, dtype=np.float64)
    frame = np.stack(np.broadcast_arrays(rows[:, None], rows[None, :], np.full((48, 48), 128.0)), axis=-1)
    frame = frame.astype(np.uint8)
    device.show({"front": frame, "wrist": np.zeros((16, 24, 3), np.uint8)},
                {"episode": np.int64(2), "step": 7, "success": np.bool_(False), "target": np.array([0.5, 1.0])})
    status, state = call(device, "/api/state")
    assert state["cameras"] == ["front", "wrist"] and state["frame_version"] == 1
    assert state["info"] == {"episode": 2, "step": 7, "success": False, "target": [0.5, 1.0]}
    status, jpeg = call(device, "/api/frame/front")
    decoded = np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"), dtype=np.float64)
    assert status == 200 and decoded.shape == frame.shape
    assert np.abs(decoded - frame).mean() < 4.0  # a smooth gradient survives JPEG closely
    assert np.asarray(Image.open(io.BytesIO(call(device, "/api/frame/wrist")[1]))).shape == (16, 24, 3)

    device.show({"front": np.full((48, 48, 3), 255, np.uint8)})  # a newer frame replaces the cached JPEG
    decoded = np.asarray(Image.open(io.BytesIO(call(device, "/api/frame/front")[1])), dtype=np.float64)
    assert decoded.min() > 250
    status, answer = call(device, "/api/frame/side")
    assert status == 404 and "['front', 'wrist']" in answer["error"]


def strict_json(content):
    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")
    return json.loads(content, parse_constant=refuse)


def test_non_finite_numbers_reach_the_page_as_strict_json(device):
    device.show({}, {"loss": float("nan"), "bound": np.array([np.inf, 1.0])})
    device.poll(policy_action=np.array([np.nan, 0.5, -np.inf]))
    with urllib.request.urlopen(f"http://127.0.0.1:{device.port}/api/state?token="
                                + urllib.request.quote(TOKEN, safe=""), timeout=10) as response:
        state = strict_json(response.read())  # a browser's JSON.parse refuses NaN and Infinity
    assert state["info"] == {"loss": "nan", "bound": ["inf", 1.0]}
    assert state["policy_action"] == ["nan", 0.5, "-inf"]


def test_show_and_poll_refuse_wrong_shapes(device):
    with pytest.raises(ValueError, match="frame 'front' must be uint8 H x W x 3"):
        device.show({"front": np.zeros((8, 8), np.uint8)})
    with pytest.raises(ValueError, match="frame 'front' must be uint8"):
        device.show({"front": np.zeros((8, 8, 3), np.float32)})
    with pytest.raises(ValueError, match=r"policy_action must have shape \(3,\)"):
        device.poll(policy_action=np.zeros(4))


def test_a_silent_holder_loses_control_to_the_policy():
    now = [0.0]
    state = WebControlState(action_dim=2, heartbeat_timeout_s=1.0, clock=lambda: now[0])
    stale = state.take_over(np.array([0.5, 0.5]))
    session = state.take_over(np.array([0.5, 0.5]))
    now[0] = 0.9
    assert state.poll(None).active
    state.set_action(np.array([0.1, 0.1]), session)  # the page's resent action is its heartbeat
    now[0] = 1.8
    assert state.poll(None).active
    with pytest.raises(StaleSession):
        state.set_action(np.array([0.1, 0.1]), stale)  # a stale page's action is no heartbeat
    now[0] = 2.0
    assert state.poll(None).active is False
    assert state.snapshot()["released_by"] == "heartbeat" and state.stats.heartbeat_releases == 1
    assert state.snapshot()["action"] == [0.0, 0.0]
    with pytest.raises(StaleSession):
        state.set_action(np.array([0.1, 0.1]), session)  # a lapsed session steers no more
    state.take_over(None)  # a new take-over restarts the clock
    assert state.poll(None).active and state.stats.takeovers == 2

    patient = WebControlState(action_dim=2, heartbeat_timeout_s=None, clock=lambda: now[0])
    patient.take_over(None)
    now[0] = 1e6
    assert patient.poll(None).active


def test_close_stops_the_server_and_start_errors_name_the_address():
    dev = WebInterventionDevice(action_dim=1, allow_no_token=True)
    port = dev.port
    assert call(dev, "/api/state", token=None)[0] == 200
    dev.close()
    dev.close()  # a second close does nothing
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=2).close()

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        with pytest.raises(RuntimeError, match=f"cannot serve on 127.0.0.1:{busy}"):
            WebInterventionDevice(action_dim=1, port=busy)


@pytest.mark.parametrize(("options", "message"), [
    ({"host": "0.0.0.0"}, "without a token lets anyone"),
    ({"token": ""}, "non-empty string"),
    ({"port": 70000}, "port must be in"),
    ({"jpeg_quality": 0}, "jpeg_quality"),
    ({"heartbeat_timeout_s": 0.05}, "heartbeat_timeout_s must exceed"),
    ({"axis_labels": ["x"]}, "axis_labels: one label per action entry"),
    ({"pad_axes": (0, 0)}, "pad_axes: two different entries"),
    ({"pad_axes": (0, 5)}, "pad_axes: two different entries"),
])
def test_bad_options_fail_before_anything_is_served(options, message):
    with pytest.raises(ValueError, match=message):
        WebInterventionDevice(action_dim=3, **options)


def test_parsers_accept_exactly_valid_values():
    np.testing.assert_array_equal(parse_action([-1, 0.5, 1], 3), [-1.0, 0.5, 1.0])
    assert parse_mark("success") == "success"
    with pytest.raises(ValueError, match="list of 2"):
        parse_action((0.0, 0.0), 2)
