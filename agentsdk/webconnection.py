"""The live web view's connection to its pages: a lost connection is never silent, and a busy page keeps it.

What the operator sees (viser's browser client is used as it is; nothing here edits it):

* **Disconnected**: viser's client keeps the last page drawn while its WebSocket is closed, wraps the panel in
  a gate that blocks the pointer (``pointer-events: none``) and dims it, and drops whatever the page tries to
  send (a key, a button reached with the keyboard) instead of queueing it. On its own it says so only with a
  small icon. :func:`connection_css` adds, keyed to that gate, a full-width red banner across the top of the
  window ("DISCONNECTED — buttons and keys do nothing: use the hardware e-stop") and greys the panel out, so the
  safety state shown is visibly the last known one, not a live one. It appears the moment the page's client
  learns the socket closed and goes as soon as it is connected again (viser then rebuilds the page from the
  server's current state: no press made while disconnected fires later).
* **No news**: a socket can stay open while nothing arrives (a stalled machine, a network that holds packets).
  Every frame the view publishes replaces the element :func:`heartbeat_html` draws; a CSS animation restarted by
  each replacement shows an orange "NO UPDATE FOR OVER :data:`STALE_AFTER` s" notice once no frame has come for
  that long, however the page's scripts are doing.

What the server does (:class:`ConnectionWatch`):

* **A busy page keeps its connection.** websockets' server (under viser) pings each page every 20 s and drops
  it if the pong takes over 20 s. A browser answers pings from its network stack, but only while it reads the
  socket: a page whose renderer is starved (software WebGL beside CPU-bound work) stops taking data, the
  browser stops reading, the pong waits behind the data, and the connection was dropped although the page was
  alive. Each page's connection gets :data:`PING_INTERVAL` and :data:`PING_TIMEOUT` instead (viser does not
  expose websockets' options, so they are set on the connection viser keeps for the page); a page that really
  is gone (its socket open, nothing answering) is still dropped within ``PING_INTERVAL + PING_TIMEOUT +
  CLOSE_TIMEOUT``: found by the ping, then given :data:`CLOSE_TIMEOUT` to answer the close (websockets' default,
  10 s, kept the page's jog step running that much longer, for a page that answers nothing); a closed page or
  browser is seen at once (its socket closes).
* **Why a page left** is logged (the close code and reason, e.g. ``1011 keepalive ping timeout``) and kept in
  :attr:`ConnectionWatch.ended`; ``on_disconnect(client_id)`` lets the view cancel a jog step that page started.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["CLOSE_TIMEOUT", "PING_INTERVAL", "PING_TIMEOUT", "STALE_AFTER", "ConnectionWatch", "PageExit",
           "connection_css", "heartbeat_html"]

log = logging.getLogger("agentsdk.webview")

#: keepalive pings to each page (s between them) and how long a page may take to answer one (s)
PING_INTERVAL = 10.0
PING_TIMEOUT = 60.0
#: how long a page may take to answer the server's close (s) before its socket is cut: a page found gone by the
#: keepalive answers nothing, and a page the server closes at shutdown has nothing left to say
CLOSE_TIMEOUT = 2.0
#: a page that has had no new frame for this long (s) says its state may be stale
STALE_AFTER = 5.0

#: the page's class names (the banner and the grey-out follow viser's gate around the marker)
MARKER = "agentsdk-connection"
BEAT = "agentsdk-beat"

BANNER = ("DISCONNECTED \\2014  buttons and keys do nothing: use the hardware e-stop. The state shown is the "
          "last known, not live (the page reconnects by itself while its window has focus).")


def connection_css() -> str:
    """The page's banner and grey-out while disconnected, and the style of the no-new-frame notice (HTML)."""
    gate = '[style*="pointer-events: none"]'
    return f"""<div class="{MARKER}" style="display: none"></div>
<style>
body:has({gate} .{MARKER})::after {{
  content: "{BANNER}";
  position: fixed; top: 0; left: 0; right: 0; z-index: 2147483647; pointer-events: none;
  padding: 0.7em 1em; background: #d00000; color: #ffffff; text-align: center;
  font: bold 1.25em/1.3 sans-serif; box-shadow: 0 0 0 0.3em #ffffff, 0 0.3em 1em rgba(0, 0, 0, 0.6);
}}
{gate}:has(.{MARKER}) {{ filter: grayscale(1); }}
.{BEAT} {{
  visibility: hidden; max-height: 0; overflow: hidden; box-sizing: border-box;
  animation: agentsdk-stale 0.001s linear {STALE_AFTER:g}s forwards;
}}
@keyframes agentsdk-stale {{
  from, to {{ visibility: visible; max-height: 20em; padding: 0.4em; background: #ff8c00; color: #000000;
              font-weight: bold; }}
}}
</style>"""


def heartbeat_html(frame: int) -> str:
    """The no-new-frame notice of frame number ``frame`` (hidden until :data:`STALE_AFTER` s after it is drawn)."""
    return (f'<div class="{BEAT}" data-frame="{int(frame)}">NO UPDATE FOR OVER {STALE_AFTER:g} s: the state '
            "shown may be stale and a press may not reach the robot.</div>")


@dataclass(frozen=True)
class PageExit:
    """How a page's connection ended: websockets' close code and reason (None and "" when not known)."""

    client_id: int
    code: int | None
    reason: str
    #: True when the server ended it (a keepalive timeout, the view closing), False when the page or the network did
    by_server: bool


def _exit(client_id: int, connection: Any) -> PageExit:
    """How ``connection`` (websockets' server connection, or None if unknown) ended."""
    protocol = getattr(connection, "protocol", None)
    sent = getattr(protocol, "close_sent", None)
    received = getattr(protocol, "close_rcvd", None)
    # the side that closed first named the reason; a close frame never answered still says why it was sent
    if sent is not None and (received is None or getattr(protocol, "close_rcvd_then_sent", None) is False):
        return PageExit(client_id, int(sent.code), str(sent.reason), True)
    if received is not None:
        return PageExit(client_id, int(received.code), str(received.reason), False)
    code = getattr(connection, "close_code", None)
    return PageExit(client_id, None if code is None else int(code), "", False)


class ConnectionWatch:
    """Watches the pages of one viser server: keepalive tolerance, why each page left (see the module docs).

    ``on_disconnect(client_id)`` is called from viser's event loop thread when a page's connection has ended;
    it must return quickly.
    """

    def __init__(self, server: Any, *, on_disconnect: Callable[[int], None] | None = None,
                 ping_interval: float = PING_INTERVAL, ping_timeout: float = PING_TIMEOUT,
                 close_timeout: float = CLOSE_TIMEOUT) -> None:
        from .errors import ConfigurationError

        if not (ping_interval > 0 and ping_timeout > 0 and close_timeout > 0):
            raise ConfigurationError("the web view's keepalive ping interval, ping timeout and close timeout must be "
                                     f"positive numbers of seconds, got {ping_interval}, {ping_timeout} and "
                                     f"{close_timeout}")
        self.server = server
        self.ping_interval = float(ping_interval)
        self.ping_timeout = float(ping_timeout)
        self.close_timeout = float(close_timeout)
        self._on_disconnect = on_disconnect
        self._lock = threading.Lock()
        self._open: dict[int, Any] = {}
        self._closed = False
        #: the last pages that left, oldest first
        self.ended: deque[PageExit] = deque(maxlen=32)
        #: pages whose keepalive could not be set (a viser that keeps its connections elsewhere)
        self.untuned = 0
        # viser's transport layer names every connection as it opens, before the page has drawn anything (viser's
        # public on_client_connect waits for the page's first camera report: a page starved while it loads the
        # meshes would keep websockets' defaults through its heaviest minute); the public hooks are the fallback
        infra = getattr(server, "_websock_server", None)
        live = getattr(infra, "_live_connections", None)
        self._live: dict[int, Any] | None = live if isinstance(live, dict) else None
        hooks: Any = infra if self._live is not None and hasattr(infra, "on_client_connect") else server
        hooks.on_client_connect(self._connected)
        hooks.on_client_disconnect(self._disconnected)

    def connected(self) -> list[int]:
        """The ids of the pages connected now."""
        with self._lock:
            return sorted(self._open)

    async def _connected(self, client: Any) -> None:
        # (in viser's event loop: the connection's keepalive task reads these before each ping)
        connection = self._live.get(client.client_id) if self._live is not None else None
        if connection is not None and hasattr(connection, "ping_timeout"):
            connection.ping_interval = self.ping_interval
            connection.ping_timeout = self.ping_timeout
            connection.close_timeout = self.close_timeout
        else:
            self.untuned += 1
            log.debug("web view: the keepalive of page %s keeps websockets' defaults", client.client_id)
        with self._lock:
            self._open[client.client_id] = connection

    async def _disconnected(self, client: Any) -> None:
        with self._lock:
            connection = self._open.pop(client.client_id, None)
            closed = self._closed
        gone = _exit(int(client.client_id), connection)
        self.ended.append(gone)
        if gone.code in (None, 1000, 1001, 1005):  # closed by the page or the server: the normal end
            log.info("web view: page %s disconnected", gone.client_id)
        else:
            log.warning("web view: page %s lost its connection (%s%s, closed by the %s)", gone.client_id, gone.code,
                        f" {gone.reason}" if gone.reason else "",
                        "server" if gone.by_server else "page or the network")
        if not closed and self._on_disconnect is not None:
            try:
                self._on_disconnect(int(client.client_id))
            except Exception:  # a failing callback must not break viser's connection teardown
                log.exception("web view: handling a page's disconnect failed")

    def close(self) -> None:
        """Stop calling ``on_disconnect`` (the server is stopping). Idempotent."""
        with self._lock:
            self._closed = True
