"""The live web view in a real browser (issue 27 acceptance 1): headless Chromium driven by selenium.

``agentsdk run --realtime --web --web-wait`` runs behaviors/wave.py's ``main`` (a few times over) and serves
the page; the browser opens it and presses Start (the page can take long to draw with software WebGL on a
loaded machine), two screenshots of the 3D view 0.5 s apart show the arm in different poses (and the joint
values on the page differ), then a click on E-STOP latches the e-stop and the arm comes to rest.
"""

from __future__ import annotations

import importlib.util
import io
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")

pytestmark = [
    pytest.mark.serial,
    pytest.mark.slow,
    pytest.mark.timeout(600),
    pytest.mark.skipif(CHROMIUM is None or CHROMEDRIVER is None, reason="needs chromium and chromedriver"),
    pytest.mark.skipif(importlib.util.find_spec("selenium") is None, reason="needs selenium"),
    pytest.mark.skipif(importlib.util.find_spec("viser") is None, reason="needs agentsdk[web] (viser)"),
]

ROW = re.compile(r"^(joint\d)\s+([+-]\d+\.\d+)\s+([+-]\d+\.\d+)\s*$", re.M)


def _stop(proc: subprocess.Popen[str], readers: list[threading.Thread]) -> None:
    """End the behavior's process (SIGINT: its category-1 stop, then a kill after 60 s) and its output readers."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    for r in readers:
        r.join(timeout=10)
    if any(r.is_alive() for r in readers):  # never close a pipe under a thread still reading it
        return
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()


def _robot_yaml(tmp_path: Path) -> str:
    """arm3 whose stall watchdog tolerates a machine loaded by a software-rendering browser (wall-time slack)."""
    import yaml

    config = yaml.safe_load((ROOT / "robots" / "arm3" / "robot.yaml").read_text())
    config["description"] = str(ROOT / "robots" / "arm3" / config["description"])
    # the page's E-STOP: category 2 (stop, then hold): with category 1 the torque goes off after the stop and a
    # simulated arm without brakes sags under gravity
    config["safety"] = {**config.get("safety", {}), "stall_timeout": 5.0, "ui_stop_category": 2}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(config))
    return str(path)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def browser() -> Iterator[Any]:
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    options = Options()
    options.binary_location = str(CHROMIUM)
    # WebGL by SwiftShader (no GPU here); the window composited in software, as Chrome does on a machine whose
    # GPU it does not use: composited through SwiftShader too, each of the browser's own frames (every screenshot
    # waits for one) took 0.4-5 s of the GPU process beside two CPU hogs, and a screenshot timed out in
    # chromedriver after 10 s
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=640,480",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                "--disable-gpu-compositing"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    driver.set_page_load_timeout(300)
    driver.set_script_timeout(300)
    config = getattr(driver.command_executor, "client_config", None)
    if config is not None:  # software WebGL on a loaded machine: a command may wait minutes for the renderer
        config.timeout = 600
    try:
        yield driver
    finally:
        driver.quit()


def _text(driver: Any) -> str:
    return str(driver.execute_script("return document.body.innerText"))


def _joints(driver: Any) -> dict[str, float]:
    return {m.group(1): float(m.group(2)) for m in ROW.finditer(_text(driver))}


def _wait(driver: Any, what: str, pred: Any, timeout: float = 240.0) -> str:
    deadline = time.monotonic() + timeout
    text = ""
    while time.monotonic() < deadline:
        text = _text(driver)
        if pred(text):
            return text
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}; the page shows:\n{text}")


def _view_png(driver: Any) -> bytes:
    """The 3D view's middle, where the arm is (left of the GUI panel), from a screenshot of the window."""
    from PIL import Image

    shot = Image.open(io.BytesIO(driver.get_screenshot_as_png()))
    w, h = shot.size
    out = io.BytesIO()
    shot.crop((int(0.15 * w), int(0.2 * h), int(0.6 * w), int(0.95 * h))).save(out, format="PNG")
    return out.getvalue()


def _changed_pixels(a: bytes, b: bytes) -> int:
    from PIL import Image, ImageChops

    ia, ib = Image.open(io.BytesIO(a)).convert("RGB"), Image.open(io.BytesIO(b)).convert("RGB")
    import numpy as np

    return int(np.count_nonzero(np.asarray(ImageChops.difference(ia, ib).convert("L")) > 24))


def test_wave_live_in_a_browser_and_the_estop_button(browser: Any, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By

    port = _free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    # behaviors/wave.py's main, a few times over: a page drawn by software WebGL on a loaded machine can be
    # slower than one 7.5 s wave
    waves = tmp_path / "waves.py"
    waves.write_text(
        "import importlib.util\n"
        f"spec = importlib.util.spec_from_file_location('wave', {str(ROOT / 'behaviors' / 'wave.py')!r})\n"
        "wave = importlib.util.module_from_spec(spec)\nspec.loader.exec_module(wave)\n\n\n"
        "from agentsdk import EStopActive\n\n\n"
        "async def main(robot):\n    try:\n        for _ in range(8):\n            await wave.main(robot)\n"
        "    except EStopActive:  # stopped from the page: stay up while the test looks\n"
        "        await robot.clock.sleep(60)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "agentsdk", "run", str(waves), "--realtime", "--robot", _robot_yaml(tmp_path),
         "--web", "--web-wait", "--port", str(port), "--quiet"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    err: list[str] = []
    reader = threading.Thread(target=lambda: err.extend(iter(proc.stderr.readline, "")), daemon=True)  # type: ignore[union-attr]
    reader.start()
    try:
        deadline = time.monotonic() + 240
        while not any("press Start on" in line for line in err):
            assert proc.poll() is None, "".join(err)
            assert time.monotonic() < deadline, "".join(err)
            time.sleep(0.1)
        assert any(f"web view: http://127.0.0.1:{port}" in line for line in err), "".join(err)
        browser.get(f"http://127.0.0.1:{port}")
        _wait(browser, "the joint table", lambda t: len(ROW.findall(t)) == 3 and "safety: OK" in t)
        _wait(browser, "the Start button", lambda t: "Start" in t)
        start = browser.find_element(By.XPATH, "//button[contains(., 'Start')]")
        browser.execute_script("arguments[0].click();", start)
        rest = _joints(browser)
        _wait(browser, "the arm to move", lambda t: _joints(browser) != rest, timeout=60)
        # the arm moves: the 3D view and the joint values change within 0.5 s
        # wave holds each pose for a while: a pair taken while the arm rests is tried again (up to 6 pairs)
        pairs = []
        for _ in range(6):
            q1, png1 = _joints(browser), _view_png(browser)
            time.sleep(0.5)
            q2, png2 = _joints(browser), _view_png(browser)
            pairs.append((max(abs(q2[j] - q1[j]) for j in q1), _changed_pixels(png1, png2)))
            if pairs[-1][0] > 1e-3 and pairs[-1][1] > 50:
                break
        assert pairs[-1][0] > 1e-3 and pairs[-1][1] > 50, pairs  # (joint change, pixels changed) per pair

        button = browser.find_element(By.XPATH, "//button[contains(., 'E-STOP')]")
        browser.execute_script("arguments[0].click();", button)  # (a toast may cover it in a small window)
        try:
            text = _wait(browser, "the e-stop", lambda t: "safety: ESTOP" in t, timeout=60)
        except AssertionError as exc:  # did the press reach the server? (its log says)
            raise AssertionError(f"{exc}\nthe server's log:\n{''.join(err)}") from None
        assert "category 2" in text
        _wait(browser, "rest", lambda t: "motion: at rest" in t, timeout=60)
        a = _joints(browser)
        time.sleep(0.5)
        b = _joints(browser)
        assert max(abs(b[j] - a[j]) for j in a) < 1e-3, (a, b)
        assert "safety: ESTOP" in _text(browser)
    finally:
        _stop(proc, [reader])
    assert not any("Traceback" in line for line in err), "".join(err)


# the behavior the keyboard test runs: to a ready pose, then a line "settled EE_X EE_Y EE_Z Q1 Q2 ..." each
# time the arm comes to rest somewhere new (robot time; the test reads them from stdout)
SETTLE_REPORTER = """
import numpy as np

from agentsdk.arm import end_effector, ready_configuration


async def main(robot):
    kin = robot.kinematics
    link = end_effector(kin)
    q = ready_configuration(kin, link, robot.latest_state().position, full=len(kin.chain(link)) >= 6)
    await robot.move_to(dict(zip(robot.joint_names, q.tolist())))
    last, still = None, 0
    while True:
        await robot.clock.sleep(0.05)
        st = robot.latest_state()
        still = still + 1 if float(np.max(np.abs(st.velocity))) < 1e-3 else 0
        if still >= 10 and (last is None or float(np.max(np.abs(st.position - last))) > 1e-4):
            last = np.array(st.position)
            ee = kin.fk(link, last).position
            print("settled", *(f"{v:.6f}" for v in [*ee, *last]), flush=True)
"""


def _settled(lines: list[str], after: int, err: list[str], timeout: float = 120.0) -> list[float]:
    """The first "settled ..." line after the ``after`` first ones, as numbers."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        done = [x for x in list(lines) if x.startswith("settled ")]
        if len(done) > after:
            return [float(v) for v in done[after].split()[1:]]
        time.sleep(0.05)
    raise AssertionError(f"no new rest pose reported; the behavior printed:\n{''.join(lines)}\n{''.join(err)}")


def test_keyboard_jog_through_the_page_moves_the_end_effector(browser: Any, tmp_path: Path) -> None:
    """Acceptance 2: real key presses in the page (no handler called directly): I is +1 cm in x within 1 mm,
    on MuJoCo (UR5); 1 and Shift+1 jog joint 1 by +-0.05 rad; each press is one step and the arm holds between."""
    import yaml
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    from agentsdk.description.catalog import find_robot

    ur5 = find_robot("ur5")
    if ur5 is None:
        pytest.skip("needs example-robot-data's UR5 (the test extra)")
    # a 6-joint arm jogs the full pose (the orientation held); wall-clock slack for a machine loaded by the browser
    robot = tmp_path / "ur5.yaml"
    robot.write_text(yaml.safe_dump({"description": str(ur5.path), "safety": {"stall_timeout": 5.0}}))
    port = _free_port()
    behavior = tmp_path / "reporter.py"
    behavior.write_text(SETTLE_REPORTER)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "agentsdk", "run", str(behavior), "--backend", "mujoco", "--realtime",
         "--robot", str(robot), "--web", "--port", str(port), "--quiet"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    out: list[str] = []
    err: list[str] = []
    readers = [threading.Thread(target=lambda: out.extend(iter(proc.stdout.readline, "")), daemon=True),  # type: ignore[union-attr]
               threading.Thread(target=lambda: err.extend(iter(proc.stderr.readline, "")), daemon=True)]  # type: ignore[union-attr]
    for r in readers:
        r.start()
    try:
        deadline = time.monotonic() + 240
        while not any(f"web view: http://127.0.0.1:{port}" in line for line in err):
            assert proc.poll() is None, "".join(err)
            assert time.monotonic() < deadline, "".join(err)
            time.sleep(0.1)
        browser.get(f"http://127.0.0.1:{port}")
        _wait(browser, "the joint table", lambda t: "shoulder_pan_joint" in t and "safety: OK" in t)
        start = _settled(out, 0, err)
        keys = ActionChains(browser)

        keys.send_keys("1").perform()  # joint1 +0.05 rad
        j1 = _settled(out, 1, err)
        assert abs(j1[3] - start[3] - 0.05) < 2e-3, (start, j1)
        assert max(abs(j1[k] - start[k]) for k in range(4, len(j1))) < 2e-3, (start, j1)

        ActionChains(browser).key_down(Keys.SHIFT).send_keys("1").key_up(Keys.SHIFT).perform()  # joint1 back
        back = _settled(out, 2, err)
        assert abs(back[3] - start[3]) < 2e-3, (start, back)

        keys.send_keys("i").perform()  # +x
        moved = _settled(out, 3, err)
        dx, dy, dz = (moved[k] - back[k] for k in range(3))
        assert abs(dx - 0.01) < 1e-3 and abs(dy) < 1e-3 and abs(dz) < 1e-3, (dx, dy, dz)

        # one press is one step: nothing more moves afterwards (release = hold)
        time.sleep(1.0)
        assert len([x for x in out if x.startswith("settled ")]) == 4, "".join(out)
    finally:
        _stop(proc, readers)
    assert not any("Traceback" in line for line in err), "".join(err)


class Relay:
    """A TCP relay between the browser and the view's server: it can hold every byte (a stalled link: the socket
    stays open, nothing arrives) or cut every connection and refuse new ones (the server side of the socket gone)."""

    def __init__(self, target: int) -> None:
        import socket

        self.target = target
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.settimeout(0.2)
        self.port = int(self.listener.getsockname()[1])
        self.flowing = threading.Event()
        self.flowing.set()
        self.refusing = False
        self._done = threading.Event()
        self._lock = threading.Lock()
        self._sockets: list[Any] = []
        self._threads = [threading.Thread(target=self._accept, name="relay-accept")]
        self._threads[0].start()

    def _accept(self) -> None:
        import socket

        while not self._done.is_set():
            try:
                down, _ = self.listener.accept()
            except TimeoutError:
                continue
            if self.refusing:
                down.close()
                continue
            up = socket.create_connection(("127.0.0.1", self.target))
            for s in (down, up):
                s.settimeout(0.2)
            with self._lock:
                self._sockets += [down, up]
                pumps = [threading.Thread(target=self._pump, args=(a, b), name="relay-pump")
                         for a, b in ((down, up), (up, down))]
                self._threads += pumps
            for p in pumps:
                p.start()

    def _pump(self, src: Any, dst: Any) -> None:
        try:
            while not self._done.is_set():
                if not self.flowing.wait(0.1):
                    continue  # held: nothing is read, so the sender's buffers fill as on a stalled link
                try:
                    data = src.recv(65536)
                except TimeoutError:
                    continue
                if not data:
                    break
                dst.sendall(data)
        except OSError:
            pass  # cut
        finally:
            for s in (src, dst):
                s.close()

    def cut(self) -> None:
        """Close every relayed connection and refuse new ones."""
        import socket

        self.refusing = True
        with self._lock:
            for s in self._sockets:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
        self.flowing.set()

    def restore(self) -> None:
        self.refusing = False
        self.flowing.set()

    def close(self) -> None:
        self._done.set()
        self.cut()
        for t in list(self._threads):
            t.join(timeout=10)
        self.listener.close()


def _banner(driver: Any) -> str:
    """The text of the page's full-width banner ("none" when it shows none)."""
    return str(driver.execute_script("return getComputedStyle(document.body, '::after').content"))


def _stale_notice(driver: Any) -> bool:
    return bool(driver.execute_script(
        "const b = document.querySelector('.agentsdk-beat');"
        "return b !== null && getComputedStyle(b).visibility === 'visible';"))


def _until(what: str, pred: Any, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)


def test_a_lost_connection_is_shown_and_a_press_meanwhile_is_not_lost_silently(browser: Any, tmp_path: Path) -> None:
    """The page's link stalls: it says no update came; the link is cut: a full-width DISCONNECTED banner, the
    E-STOP click and a jog key pressed meanwhile do nothing then and nothing after the page reconnects; once
    connected again the banner goes and the same click latches the e-stop."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    port = _free_port()
    behavior = tmp_path / "hold.py"
    behavior.write_text("async def main(robot):\n    await robot.clock.sleep(3600)\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "agentsdk", "run", str(behavior), "--backend", "mock", "--realtime",
         "--robot", _robot_yaml(tmp_path), "--web", "--port", str(port), "--quiet"],
        cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )
    err: list[str] = []
    reader = threading.Thread(target=lambda: err.extend(iter(proc.stderr.readline, "")), daemon=True)  # type: ignore[union-attr]
    reader.start()
    relay: Relay | None = None
    try:
        deadline = time.monotonic() + 240
        while not any(f"web view: http://127.0.0.1:{port}" in line for line in err):
            assert proc.poll() is None, "".join(err)
            assert time.monotonic() < deadline, "".join(err)
            time.sleep(0.1)
        relay = Relay(port)
        browser.get(f"http://127.0.0.1:{relay.port}")
        _wait(browser, "the joint table", lambda t: len(ROW.findall(t)) == 3 and "safety: OK" in t)
        assert "DISCONNECTED" not in _banner(browser)
        _until("fresh frames", lambda: not _stale_notice(browser))
        before = _joints(browser)

        relay.flowing.clear()  # the link stalls: the socket stays open, nothing arrives
        _until("the no-update notice", lambda: _stale_notice(browser), timeout=60)
        assert "NO UPDATE FOR OVER" in _text(browser)

        relay.cut()  # the server side of the socket is gone
        _until("the DISCONNECTED banner", lambda: "DISCONNECTED" in _banner(browser), timeout=60)
        assert "hardware e-stop" in _banner(browser)
        button = browser.find_element(By.XPATH, "//button[contains(., 'E-STOP')]")
        ActionChains(browser).move_to_element(button).click().perform()  # a real click: blocked by the page
        browser.execute_script("arguments[0].click();", button)  # even one that gets through is not sent
        ActionChains(browser).send_keys("1").perform()  # jog joint1: dropped, not queued
        time.sleep(2.0)

        relay.restore()
        _until("the banner to go", lambda: "DISCONNECTED" not in _banner(browser))
        _wait(browser, "the page again", lambda t: len(ROW.findall(t)) == 3 and "safety: OK" in t)
        time.sleep(3.0)  # nothing pressed while disconnected fires now
        text = _text(browser)
        assert "safety: OK" in text, text
        after = _joints(browser)
        assert max(abs(after[j] - before[j]) for j in before) < 1e-3, (before, after)
        assert not any("e-stop (category" in line for line in err), "".join(err)

        button = browser.find_element(By.XPATH, "//button[contains(., 'E-STOP')]")
        ActionChains(browser).move_to_element(button).click().perform()  # connected: the same click works
        _wait(browser, "the e-stop", lambda t: "safety: ESTOP" in t, timeout=60)
    finally:
        if relay is not None:
            relay.close()
        _stop(proc, [reader])
    assert not any("Traceback" in line for line in err), "".join(err)
