"""The live web view's connections without a browser: a busy page keeps its connection, a dead one is dropped,
and a jog step a page started stops when that page goes.

A scripted page speaks viser's WebSocket protocol (like tests/test_webview_pacing.py): it can stop reading its
socket (a page whose renderer is starved: the browser then answers no keepalive ping either), trigger a jog
command as a key press does, and disconnect.
"""

from __future__ import annotations

import asyncio
import importlib.util
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import agentsdk
from agentsdk.errors import ConfigurationError

pytestmark = [pytest.mark.timeout(300),
              pytest.mark.skipif(importlib.util.find_spec("viser") is None, reason="needs agentsdk[web] (viser)")]

SAFETY = {"stall_timeout": 5.0, "ui_stop_category": 2}
ROOT = Path(__file__).resolve().parents[1]


async def _until(pred: Callable[[], bool], within: float = 120.0) -> None:
    async with asyncio.timeout(within):
        while not pred():  # noqa: ASYNC110  (set by other threads and tasks: no event to wait on)
            await asyncio.sleep(0.02)


class ScriptedPage:
    """A browser page reduced to its protocol: counts frames, knows the commands, can stop reading."""

    def __init__(self, url: str) -> None:
        self.url = url.replace("http://", "ws://")
        self.frames = 0
        self.commands: dict[str, str] = {}  # label -> uuid
        self.ws: Any = None
        self.ended = asyncio.Event()

    async def send(self, message: dict[str, Any]) -> None:
        import msgspec

        await self.ws.send(msgspec.msgpack.encode(message))

    async def run(self) -> None:
        import msgspec
        import viser
        import zstandard
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed

        unzip = zstandard.ZstdDecompressor()
        try:
            async with connect(self.url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None,  # type: ignore[list-item]
                               ping_interval=None, close_timeout=1.0) as ws:  # (the test's own close: no 10 s wait)
                self.ws = ws
                await self.send(
                    {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (1.0, -1.0, 1.0),
                     "fov": 1.0, "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640,
                     "look_at": (0.0, 0.0, 0.0), "up_direction": (0.0, 0.0, 1.0)})
                async for data in ws:
                    assert isinstance(data, bytes)
                    size, packed = int.from_bytes(data[:8], "little"), int.from_bytes(data[8:16], "little")
                    batch = msgspec.msgpack.decode(unzip.decompress(data[16:16 + packed], max_output_size=size))
                    for message in batch["messages"]:
                        if message["type"] == "LocalStorageGetItemRequestMessage":  # the pacer's round trip
                            await self.send({"type": "LocalStorageGetItemResponseMessage", "value": None,
                                             "error": None, "request_uuid": message["request_uuid"]})
                        elif message["type"] == "RegisterCommandMessage":
                            self.commands[message["props"]["label"]] = message["uuid"]
                        elif "**time:**" in str(message):
                            self.frames += 1
        except ConnectionClosed:
            pass  # closed by the test (an answer to the last request may find the socket closed) or the server
        finally:
            self.ended.set()

    def stall(self) -> None:
        """Stop reading the socket (a starved page): nothing is taken in, no keepalive ping is answered."""
        self.ws.transport.pause_reading()

    def resume(self) -> None:
        self.ws.transport.resume_reading()


async def _with_page(body: Callable[[Any, Any, ScriptedPage], Any], *, robot: str = "arm3",
                     tune: Callable[[Any], None] | None = None) -> None:
    from agentsdk.webview import WebView

    WebView.prepare()
    async with agentsdk.connect("mock", robot=robot, safety=SAFETY, realtime=True) as arm:
        view = WebView.attach(arm, port=0)
        try:
            await view.wait_ready()
            if tune is not None:
                tune(view)
            page = ScriptedPage(view.url)
            async with asyncio.TaskGroup() as tg:
                reader = tg.create_task(page.run())
                try:
                    await _until(lambda: page.frames >= 2)
                    await body(arm, view, page)
                finally:
                    reader.cancel()
        finally:
            view.close()


async def test_a_page_too_busy_to_answer_pings_keeps_its_connection() -> None:
    """A page that reads nothing for many ping intervals, but less than the ping timeout, stays and catches up.

    At a tenth of the web view's defaults (0.5 s pings as 10 s, a 4.5 s stall as 45 s), with a timeout of 8 s
    so that a loaded machine's late resume is not what is tested; the next test checks that a page's connection
    gets the defaults, whose timeout outlasts websockets' own ping + pong (the 45 s stall it used to drop)."""
    def tune(view: Any) -> None:
        view.connections.ping_interval = 0.5
        view.connections.ping_timeout = 8.0

    async def body(arm: Any, view: Any, page: ScriptedPage) -> None:
        page.stall()
        await asyncio.sleep(4.5)  # nine pings go out meanwhile, none answered
        frames = page.frames
        page.resume()
        # it catches up and frames flow again (with websockets' 20 s + 20 s scaled the same way, it read the close)
        await _until(lambda: page.frames > frames + 2 or page.ended.is_set())
        assert not page.ended.is_set()
        assert list(view.connections.ended) == []
        assert view.connections.connected() == [0]

    await _with_page(body, tune=tune)


async def test_a_page_gets_the_web_views_keepalive_which_outlasts_websockets_defaults() -> None:
    """The connection viser keeps for a page carries PING_INTERVAL, PING_TIMEOUT and CLOSE_TIMEOUT (viser does
    not pass websockets' options on): a busy page may go unanswered longer than websockets' defaults allow, and a
    page found gone is cut sooner than websockets' close timeout would (its jog step cancelled sooner)."""
    import inspect

    from websockets.asyncio.server import serve

    from agentsdk.webconnection import CLOSE_TIMEOUT, PING_INTERVAL, PING_TIMEOUT

    defaults = inspect.signature(serve).parameters
    ws_allowance = defaults["ping_interval"].default + defaults["ping_timeout"].default
    assert PING_TIMEOUT > ws_allowance, (PING_TIMEOUT, ws_allowance)
    assert CLOSE_TIMEOUT < defaults["close_timeout"].default

    async def body(arm: Any, view: Any, page: ScriptedPage) -> None:
        assert view.connections.untuned == 0
        (connection,) = view.connections._open.values()
        assert (connection.ping_interval, connection.ping_timeout, connection.close_timeout) == (
            PING_INTERVAL, PING_TIMEOUT, CLOSE_TIMEOUT)

    await _with_page(body)


async def test_a_page_that_answers_nothing_is_dropped_and_the_reason_kept() -> None:
    """A dead page (socket open, nothing answering) is still detected: dropped after the ping timeout."""
    def tune(view: Any) -> None:
        view.connections.ping_interval = 0.3
        view.connections.ping_timeout = 1.0

    async def body(arm: Any, view: Any, page: ScriptedPage) -> None:
        page.stall()
        await _until(lambda: len(view.connections.ended) == 1, within=60.0)
        (gone,) = view.connections.ended
        assert (gone.client_id, gone.code, gone.reason, gone.by_server) == (0, 1011, "keepalive ping timeout", True)
        assert view.connections.connected() == []

    await _with_page(body, tune=tune)


def _slow_arm(tmp_path: Path) -> str:
    """arm3 whose joints move at 0.02 rad/s at most: a 0.05 rad jog step takes seconds."""
    import yaml

    config = yaml.safe_load((ROOT / "robots" / "arm3" / "robot.yaml").read_text())
    config["description"] = str(ROOT / "robots" / "arm3" / config["description"])
    config["joint_limits"] = {"default": {"max_velocity": 0.02, "max_acceleration": 8.0, "max_jerk": 150.0}}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(config))
    return str(path)


async def test_a_jog_step_from_a_page_that_disconnects_is_cancelled_and_the_arm_holds(tmp_path: Path) -> None:
    async def body(arm: Any, view: Any, page: ScriptedPage) -> None:
        start = float(arm.latest_state().position[0])
        await page.send({"type": "CommandTriggerMessage", "uuid": page.commands["Jog joint1 +"]})
        await _until(lambda: float(arm.latest_state().position[0]) > start + 0.002)  # the step runs
        jogging = view._jogging
        assert jogging is not None and not jogging.done()
        await page.ws.close()  # the page goes (closed, reloaded, its network gone)
        await _until(lambda: jogging.done(), within=30.0)
        assert jogging.cancelled()
        await _until(lambda: float(np.max(np.abs(arm.latest_state().velocity))) < 1e-3, within=30.0)
        held = float(arm.latest_state().position[0])
        assert start < held < start + 0.045  # stopped short of the 0.05 rad step, and holds there
        await asyncio.sleep(0.5)
        assert abs(float(arm.latest_state().position[0]) - held) < 1e-3
        assert arm.safety.state.name == "OK"  # a hold, not a stop: the robot stays usable

    await _with_page(body, robot=_slow_arm(tmp_path))


async def test_a_jog_from_python_is_not_cancelled_by_a_page_that_goes(tmp_path: Path) -> None:
    async def body(arm: Any, view: Any, page: ScriptedPage) -> None:
        start = float(arm.latest_state().position[0])
        view.jog_joint("joint1", 0.01)  # from Python (or another input): no page owns it
        await _until(lambda: float(arm.latest_state().position[0]) > start + 0.001)
        jogging = view._jogging
        await page.ws.close()
        await _until(lambda: len(view.connections.ended) == 1)
        await _until(lambda: jogging.done(), within=60.0)
        assert not jogging.cancelled()
        assert float(arm.latest_state().position[0]) == pytest.approx(start + 0.01, abs=2e-3)

    await _with_page(body, robot=_slow_arm(tmp_path))


def test_the_keepalive_settings_are_checked() -> None:
    from agentsdk.webconnection import ConnectionWatch

    with pytest.raises(ConfigurationError, match="keepalive"):
        ConnectionWatch(object(), ping_timeout=0.0)
    with pytest.raises(ConfigurationError, match="close timeout"):
        ConnectionWatch(object(), close_timeout=float("nan"))


def test_the_page_css_keys_the_banner_to_viser_s_disconnected_gate() -> None:
    from agentsdk.webconnection import MARKER, STALE_AFTER, connection_css, heartbeat_html

    css = connection_css()
    assert f'body:has([style*="pointer-events: none"] .{MARKER})::after' in css
    assert "DISCONNECTED" in css and "hardware e-stop" in css
    assert f"{STALE_AFTER:g}s forwards" in css
    # each frame's notice differs, so the page replaces it (and restarts its stale timer)
    assert heartbeat_html(1) != heartbeat_html(2)
