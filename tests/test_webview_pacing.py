"""Flow control of the live web view without a browser: a page gets no new frame before it has applied the last.

A scripted page speaks viser's WebSocket protocol: it decodes the frames and answers the view's per-frame
request (or holds it back, like a page whose main thread is starved), so the test sees exactly what a slow
page is sent while it is busy.
"""

from __future__ import annotations

import asyncio
import importlib.util
from collections.abc import Callable
from typing import Any

import pytest

import agentsdk
from agentsdk.errors import ConfigurationError

pytestmark = [pytest.mark.timeout(300),
              pytest.mark.skipif(importlib.util.find_spec("viser") is None, reason="needs agentsdk[web] (viser)")]

SAFETY = {"stall_timeout": 5.0, "ui_stop_category": 2}


async def _until(pred: Callable[[], bool]) -> None:
    async with asyncio.timeout(120.0):
        while not pred():  # noqa: ASYNC110  (set by other threads and tasks: no event to wait on)
            await asyncio.sleep(0.02)


class ScriptedPage:
    """A browser page reduced to its protocol: it records the frames (status texts) and the sync requests."""

    def __init__(self, url: str) -> None:
        self.url = url.replace("http://", "ws://")
        self.events: list[tuple[str, str]] = []  # ("frame", status text) or ("sync", request id), in arrival order
        self.answer = True  # False: hold the requests back (a page too busy to get to them)
        self.held: list[str] = []
        self._ws: Any = None

    def frames(self) -> int:
        return sum(1 for kind, _ in self.events if kind == "frame")

    def syncs(self) -> int:
        return sum(1 for kind, _ in self.events if kind == "sync")

    async def release(self) -> None:
        """Answer the held requests (the page got to them)."""
        self.answer = True
        held, self.held = self.held, []
        for uuid in held:
            await self._reply(uuid)

    async def _reply(self, uuid: str) -> None:
        import msgspec

        await self._ws.send(msgspec.msgpack.encode(
            {"type": "LocalStorageGetItemResponseMessage", "value": None, "error": None, "request_uuid": uuid}))

    async def run(self) -> None:
        import msgspec
        import viser
        import zstandard
        from websockets.asyncio.client import connect

        unzip = zstandard.ZstdDecompressor()
        async with connect(self.url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None) as ws:  # type: ignore[list-item]
            self._ws = ws
            # what a page sends once it has drawn its canvas (viser counts a page as a client from then on)
            await ws.send(msgspec.msgpack.encode(
                {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (1.0, -1.0, 1.0),
                 "fov": 1.0, "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640,
                 "look_at": (0.0, 0.0, 0.0), "up_direction": (0.0, 0.0, 1.0)}))
            async for data in ws:
                assert isinstance(data, bytes)
                size, packed = int.from_bytes(data[:8], "little"), int.from_bytes(data[8:16], "little")
                batch = msgspec.msgpack.decode(unzip.decompress(data[16:16 + packed], max_output_size=size))
                for message in batch["messages"]:
                    if message["type"] == "LocalStorageGetItemRequestMessage":
                        uuid = message["request_uuid"]
                        self.events.append(("sync", uuid))
                        if self.answer:
                            await self._reply(uuid)
                        else:
                            self.held.append(uuid)
                    elif "**time:**" in str(message):
                        self.events.append(("frame", str(message)))


async def _with_page(body: Callable[[Any, ScriptedPage], Any], *, max_wait: float) -> None:
    from agentsdk.webview import WebView

    WebView.prepare()
    async with agentsdk.connect("mock", robot="arm3", safety=SAFETY, realtime=True) as robot:
        view = WebView.attach(robot, port=0)
        try:
            await view.wait_ready()
            assert view.pacer is not None
            view.pacer.max_wait = max_wait
            page = ScriptedPage(view.url)
            async with asyncio.TaskGroup() as tg:
                reader = tg.create_task(page.run())
                try:
                    await body(view, page)
                finally:
                    reader.cancel()
        finally:
            view.close()


async def test_a_busy_page_gets_no_new_frame_until_it_has_applied_the_last() -> None:
    async def body(view: Any, page: ScriptedPage) -> None:
        await _until(lambda: page.syncs() >= 5)  # a page that answers at once is sent frame after frame
        assert page.frames() >= 3
        page.answer = False  # now it is busy: it does not get to the next request
        await _until(lambda: bool(page.held))
        at_hold = len(page.events)
        await asyncio.sleep(1.5)  # 30 frames/s would be 45 frames by now
        during = page.events[at_hold:]
        # nothing new while it is busy (the frame the request followed may still be on its way: at most one)
        assert sum(1 for kind, _ in during if kind == "frame") <= 1, during
        assert not any(kind == "sync" for kind, _ in during), during
        frames = page.frames()
        await page.release()
        await _until(lambda: page.frames() > frames + 2)  # it answered: frames flow again, the newest state

    await _with_page(body, max_wait=60.0)


async def test_a_page_that_never_answers_does_not_stop_the_view() -> None:
    """A page that never answers is waited for at most max_wait per frame: it gets one frame per wait, no flood."""
    async def body(view: Any, page: ScriptedPage) -> None:
        page.answer = False
        await _until(lambda: page.syncs() >= 3)
        assert view.pacer.timeouts >= 2
        assert view.last is not None

    await _with_page(body, max_wait=0.3)


def test_the_pause_between_frames() -> None:
    from agentsdk.webpacing import PagePacer

    # a quick page: the frame rate
    assert PagePacer.next_delay(0.1, 0.02, 0.01) == pytest.approx(0.08)
    # a page that needs 1 s per frame gets as long again to itself before the next one
    assert PagePacer.next_delay(0.1, 1.2, 1.0) == pytest.approx(1.0)
    assert PagePacer.next_delay(0.1, 0.5, 0.0) == 0.0
    with pytest.raises(ConfigurationError, match="max_wait"):
        PagePacer(object(), max_wait=0.0)
