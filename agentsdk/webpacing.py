"""Flow control for the live web view: a page gets a new frame only once it has applied the previous one.

viser's browser client reads its WebSocket in a worker as fast as the data comes and hands every batch to
the page's main thread, which applies scene updates in its render loop. The server therefore never feels
back-pressure: when the page cannot keep up (software WebGL on a machine whose cores are busy, a slow
laptop) the batches pile up in the page faster than it can draw them, every queued batch asks for another
frame, and the page stops answering anything else (clicks, scripts) for as long as the stream lasts.

:class:`PagePacer` closes the loop. After each published frame the publisher calls :meth:`PagePacer.sync`:
every connected page is sent a tiny request (a localStorage read, part of viser's public API) that the page
answers from the same ordered queue that applies the frame, so the answer comes back once the page has
worked through everything sent before it. The publisher waits for every page's answer (at most
:attr:`PagePacer.max_wait` seconds, so a page that never answers cannot stop the others) and then leaves
the pages at least as much time again before the next frame (:meth:`PagePacer.next_delay`): a page spends
at most about half of its time applying updates and always has time left for its user. Frames are never
queued for a slow page; the next frame it gets is the newest state.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from .errors import ConfigurationError

__all__ = ["PagePacer"]

log = logging.getLogger("agentsdk.webview")

#: the localStorage key the round trip reads (nothing is ever written under it)
SYNC_KEY = "agentsdk-frame-sync"


class PagePacer:
    """Paces a viser server's frames to what its slowest connected page can apply (see the module docs)."""

    def __init__(self, server: Any, *, max_wait: float = 2.0) -> None:
        if not max_wait > 0:
            raise ConfigurationError(f"the web view's max_wait must be a positive number of seconds, got {max_wait}")
        self.server = server
        self.max_wait = float(max_wait)
        #: the last round trip (s): from the end of publishing a frame to every page having applied it
        self.last_round_trip = 0.0
        #: round trips that ran into :attr:`max_wait` (a page that did not answer in time)
        self.timeouts = 0

    def sync(self, closed: threading.Event | None = None) -> float:
        """Wait until every connected page has applied what was published so far; return the wait (s).

        Bounded by :attr:`max_wait` in all (then the pages that did not answer are not waited for this
        time); returns early when ``closed`` is set or no page is connected. Call from the publishing thread,
        never from an event loop.
        """
        start = time.monotonic()
        deadline = start + self.max_wait
        with_storage = []
        for client in list(self.server.get_clients().values()):
            storage = getattr(client, "local_storage", None)  # (viser versions without it are not paced)
            if storage is not None:
                with_storage.append(storage)
        if not with_storage:
            self.last_round_trip = 0.0
            return 0.0
        self.server.flush()  # the frame leaves before the requests that follow it
        for storage in with_storage:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or (closed is not None and closed.is_set()):
                break
            try:
                storage.get_item(SYNC_KEY, timeout=remaining)
            except TimeoutError:
                self.timeouts += 1
                log.debug("web view: a page did not apply a frame within %.1f s", self.max_wait)
                break
            except RuntimeError:  # the page disconnected (or its browser refuses localStorage): not waited for
                log.debug("web view: frame sync with a page failed", exc_info=True)
        self.last_round_trip = time.monotonic() - start
        return self.last_round_trip

    @staticmethod
    def next_delay(period: float, elapsed: float, round_trip: float) -> float:
        """How long to wait before the next frame (s), ``elapsed`` s after the last one began.

        At most one frame per ``period``; and at least ``round_trip`` more after the pages applied the last
        one, so a page that needs longer than ``period`` per frame is busy at most about half of its time.
        """
        return max(period - elapsed, round_trip, 0.0)
