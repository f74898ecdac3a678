"""The intervention web page in a real headless browser (Debian's Chromium, driven by Playwright)
while a simulated Sawyer runs its control loop in real time: the page shows the robot's camera, and
take-over, the joystick pad, the sliders, hand-back and the success button reach the control loop
through poll(), which is what the learner stores (who acted, the human's action, the episode marks).

Needs ``apt-get install chromium`` and ``pip install playwright`` (no ``playwright install``: the
system Chromium is used); skipped with the missing piece named otherwise."""

import contextlib
import importlib.util
import tempfile
import threading
import time

import numpy as np
import pytest

from tests.integration.browser import BROWSER_SKIPS, CHROMIUM

pytestmark = [
    *BROWSER_SKIPS,
    # Not imported here: MetaWorld loads MuJoCo, which picks its GL backend once per process (see
    # the simulated robots), so the robot is built inside the test.
    pytest.mark.skipif(importlib.util.find_spec("metaworld") is None, reason="needs metaworld"),
    pytest.mark.timeout(120),
]

TOKEN = "browser-test-token"
CAMERA = "corner"
WAIT_S = 15.0


def wait_for(predicate, what):
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


class ControlLoop:
    """A robot's control loop with a stand-in policy that holds still: every step it shows the
    camera to the device, polls it, and steps the env with the human's action when they act."""

    def __init__(self, env, device):
        self.env, self.device = env, device
        self.received = []  # (HumanInput, the target the step started from)
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.error = None
        self.thread = threading.Thread(target=self.run, name="control-loop", daemon=True)

    def run(self):
        try:
            obs, step = self.env.reset(), 0
            while not self.stop.is_set():
                policy_action = np.zeros(4)
                self.device.show({CAMERA: obs[f"pixels.{CAMERA}"]}, {"episode": 0, "step": step})
                human = self.device.poll(observation=obs, policy_action=policy_action)
                with self.lock:
                    self.received.append((human, obs["state"][:3].copy()))
                obs = self.env.step(human.action if human.active else policy_action).obs
                step += 1
        except BaseException as error:  # reported by the test, which would otherwise only time out
            self.error = error

    def inputs(self):
        assert self.error is None, f"the control loop failed: {self.error!r}"
        with self.lock:
            return [human for human, _ in self.received]

    def last(self):
        inputs = self.inputs()
        return inputs[-1] if inputs else None

    def targets(self):
        with self.lock:
            return [target for _, target in self.received]


def wait_for_text(page, selector, text):
    """Wait until the element shows exactly ``text`` (the page updates after its requests return)."""
    page.wait_for_function("([selector, text]) => document.querySelector(selector).textContent === text",
                           arg=[selector, text], timeout=WAIT_S * 1000)


def acting_with(loop, action):
    """The latest step was the human's, with ``action`` (to the pad's pixel resolution)."""
    def check():
        human = loop.last()
        return human is not None and human.active and np.allclose(human.action, action, atol=0.02)
    return check


@pytest.fixture
def sawyer_env():
    from infinirl.realworld.driver import make_robot
    from infinirl.realworld.robot_env import RobotEnv, RobotEnvSpec
    from infinirl.realworld.safety import SafeRobot, SafetyConfig

    robot = SafeRobot(make_robot("sim_sawyer", control_hz=20.0, image_size=64),
                      SafetyConfig(command_deadline_s=None, heartbeat_deadline_s=None))
    robot.connect()
    try:
        yield RobotEnv(robot, RobotEnvSpec(cameras=(CAMERA,), max_episode_steps=100_000, terminate_on_success=False))
    finally:
        robot.close()


@contextlib.contextmanager
def page_address(device, via):
    """Where the browser opens the page: the device itself, or (``via="link"``) the cloud's page port
    of a cloud-edge link, the edge (beside the robot) dialling the cloud hub through a link
    emulator of 60 ms round trip and 20 Mbit/s, with no port open at the edge."""
    if via == "direct":
        yield device.url
        return
    from infinirl.edge.cloud_hub import CloudHub, HubOptions
    from infinirl.edge.cloud_hub import wait_for as wait_until
    from infinirl.edge.credentials import issue_credentials
    from infinirl.edge.edge_client import EdgeClient, EdgeOptions
    from infinirl.edge.emulator import EmulatorSpec, LinkEmulator
    from infinirl.edge.link import LinkOptions
    from infinirl.edge.tunnel import TunnelListener

    link = LinkOptions(connect_timeout_s=5.0, heartbeat_s=0.3, dead_after_s=3.0)
    with tempfile.TemporaryDirectory() as pki:
        credentials = issue_credentials(pki, edges=("edge-0",))
        hub = CloudHub(("127.0.0.1", 0), credentials["cloud"], on_episode=lambda *args: None,
                       options=HubOptions(link=link)).start()
        emulator = LinkEmulator(EmulatorSpec.from_rtt(rtt_ms=60, mbit_per_s=20), hub.address)
        client = EdgeClient(emulator.address, credentials["edge-0"], name="edge-0", options=EdgeOptions(link=link),
                            tunnel_targets={"page": (device.host, device.port)}).start()
        listener = TunnelListener(("127.0.0.1", 0), lambda: hub.tunnel("edge-0"), service="page").start()
        try:
            assert client.wait_connected(WAIT_S) and wait_until(lambda: hub.tunnel() is not None, WAIT_S)
            host, port = listener.address
            yield f"http://{host}:{port}/?token={TOKEN}"
            assert not hub.tunnel("edge-0").failures and not client.tunnel.failures
        finally:
            listener.close()
            client.close()
            emulator.close()
            hub.close()


@pytest.mark.parametrize("via", ["direct", "link"])
def test_take_over_move_hand_back_and_mark_success_from_the_page(sawyer_env, via):
    """``link``: the same clicks from a browser on the cloud side of an emulated slow WAN link."""
    from playwright.sync_api import sync_playwright

    from infinirl.realworld.intervention.web import WebInterventionDevice

    with WebInterventionDevice(action_dim=4, token=TOKEN, axis_labels=["dx", "dy", "dz", "gripper"]) as device:
        loop = ControlLoop(sawyer_env, device)
        loop.thread.start()
        try:
            with page_address(device, via) as url, sync_playwright() as playwright:
                browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True)
                try:
                    drive_the_page(browser.new_page(viewport={"width": 1000, "height": 900}), url, loop)
                finally:
                    browser.close()
        finally:
            loop.stop.set()
            loop.thread.join(10)
    assert loop.error is None, f"the control loop failed: {loop.error!r}"
    assert device.stats.takeovers == 1 and device.stats.handbacks == 1 and device.stats.heartbeat_releases == 0
    assert device.stats.rejected_requests == 0


def drive_the_page(page, url, loop):
    page.set_default_timeout(WAIT_S * 1000)
    page.goto(url)
    # The camera view loads a frame of the robot's camera.
    page.wait_for_function(f"() => {{ const img = document.getElementById('camera-{CAMERA}');"
                           " return img && img.complete && img.naturalWidth === 64 && img.dataset.version > 0; }")
    first_version = int(page.get_attribute(f"#camera-{CAMERA}", "data-version"))
    wait_for_text(page, "#actor", "policy acts")
    assert all(not human.active for human in loop.inputs())

    page.click("#takeover")
    wait_for(acting_with(loop, [0, 0, 0, 0]), "the human's centred joystick after take-over")
    wait_for_text(page, "#actor", "HUMAN acts (this page)")

    # Drag the pad's knob halfway right and halfway up, and hold it there.
    box = page.locator("#pad").bounding_box()
    centre_x, centre_y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(centre_x, centre_y)
    page.mouse.down()
    page.mouse.move(centre_x + box["width"] / 4, centre_y - box["height"] / 4, steps=5)
    wait_for(acting_with(loop, [0.5, 0.5, 0, 0]), "the pad's action (dx, dy) = (0.5, 0.5)")
    held_from = len(loop.inputs())
    start_target = loop.targets()[held_from - 1]
    wait_for(lambda: len(loop.inputs()) > held_from + 5, "control steps with the pad held")
    moved = loop.targets()[-1] - start_target
    assert moved[0] > 0 and moved[1] > 0, moved  # the arm went right and forward (its height settles freely)

    page.mouse.up()  # the pad springs back to the centre
    wait_for(acting_with(loop, [0, 0, 0, 0]), "the centred pad after release")
    page.focus("#slider-3")
    page.keyboard.press("End")  # gripper fully open
    page.focus("#slider-2")
    page.keyboard.press("Home")  # dz fully down
    wait_for(acting_with(loop, [0, 0, -1, 1]), "the sliders' action (dz, gripper) = (-1, 1)")

    page.click("#handback")
    wait_for(lambda: loop.last() is not None and not loop.last().active, "the policy acting after hand-back")
    wait_for_text(page, "#actor", "policy acts")

    marks_before = len(loop.inputs())
    page.click("#success")
    wait_for(lambda: any(human.marks for human in loop.inputs()[marks_before:]), "the success mark")
    steps_after = len(loop.inputs())
    wait_for(lambda: len(loop.inputs()) > steps_after + 3, "more control steps")
    marks = [human.marks for human in loop.inputs() if human.marks]
    assert marks == [("success",)]  # delivered once, in the step after the click
    wait_for_text(page, "#notice", "success marked")

    # The view kept following the camera, and the page saw no error.
    page.wait_for_function(f"() => document.getElementById('camera-{CAMERA}').dataset.version > {first_version}")
    wait_for_text(page, "#error", "")  # a request that timed out on a busy host is shown until the next answer


def test_the_page_shows_an_evaluation_and_refuses_a_take_over_until_training_resumes(sawyer_env):
    """The control loop holds the device off for an evaluation: the page says so, gives back the
    control it held and disables its take-over button; a take-over sent anyway (a button the page had
    not disabled yet) is refused with the reason. Training again: the page steers as before."""
    from playwright.sync_api import sync_playwright

    from infinirl.realworld.intervention.web import WebInterventionDevice

    with WebInterventionDevice(action_dim=4, token=TOKEN) as device:
        loop = ControlLoop(sawyer_env, device)
        loop.thread.start()
        try:
            with sync_playwright() as playwright:
                browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True)
                try:
                    page = browser.new_page()
                    page.set_default_timeout(WAIT_S * 1000)
                    page.goto(device.url)
                    wait_for_text(page, "#actor", "policy acts")
                    page.click("#takeover")
                    wait_for_text(page, "#actor", "HUMAN acts (this page)")

                    device.hold_off("evaluation")  # as the control loop does before an evaluation's reset
                    wait_for_text(page, "#actor", "evaluation: policy acts alone")
                    page.wait_for_function("() => document.getElementById('takeover').disabled")
                    held = page.text_content("#held-off")
                    assert "evaluation episode is running" in held and "next training episode" in held
                    assert "control went back to the policy: an evaluation" in page.text_content("#notice")
                    wait_for(lambda: loop.last() is not None and not loop.last().active, "the policy acting")

                    page.evaluate("() => { document.getElementById('takeover').disabled = false; }")
                    page.click("#takeover")
                    wait_for_text(page, "#notice", held)  # the 409's reason
                    assert device.stats.refused_takeovers == 1 and not loop.last().active

                    device.hold_off(None)  # the next training episode starts
                    wait_for_text(page, "#actor", "policy acts")
                    wait_for_text(page, "#held-off", "")
                    page.click("#takeover")
                    wait_for_text(page, "#actor", "HUMAN acts (this page)")
                    wait_for(lambda: loop.last() is not None and loop.last().active, "the human acting")
                    wait_for_text(page, "#error", "")
                finally:
                    browser.close()
        finally:
            loop.stop.set()
            loop.thread.join(10)
    assert loop.error is None, f"the control loop failed: {loop.error!r}"
