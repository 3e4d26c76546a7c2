"""A live web view of a running robot: 3D meshes, joint plots, safety and motion state, an e-stop button.

``agentsdk run BEHAVIOR --web [--port 8080]`` serves a page on http://127.0.0.1:PORT while the
behavior runs; :meth:`WebView.attach` does the same from Python::

    view = WebView.attach(robot, port=8080)
    ...
    view.close()

The page shows the robot in 3D with its meshes (viser's ``ViserUrdf`` on yourdfpy), the
joint positions over the last seconds (uPlot), the safety state (OK, HOLD, ESTOP, DISABLED,
FAULT) with the cause of a latched stop, what the motions are doing, the active state of any
state machine running on the robot, and an **E-STOP** button. The button latches an e-stop of
the robot's configured category (``safety.ui_stop_category`` in robot.yaml, default 1).
**Reset** and **Enable** sit behind a confirmation dialog.

Threads and rates: viser serves the page from its own thread. A publisher thread wakes up
:data:`RATE` times a second (wall time), asks the robot's event loop for a snapshot (a tiny
callback that copies positions, velocities and states: nothing runs inside the control tick),
and pushes it to the page; plots are redrawn at :data:`PLOT_RATE`. A slow or absent browser
never slows the control loop; at most one snapshot request is pending at a time. A page gets the next
frame only once it has applied the last one (:mod:`agentsdk.webpacing`): a page too slow for 30 frames a
second gets fewer, newer ones rather than a backlog that would leave it unable to answer a click.

Connection loss is never silent (:mod:`agentsdk.webconnection`): while the page is not connected it shows a
full-width red **DISCONNECTED** banner and greys the last known state out (viser's client already blocks its
buttons then); a page that has had no new frame for :data:`~agentsdk.webconnection.STALE_AFTER` seconds says so;
the server tolerates a page too busy to answer its keepalive pings for up to
:data:`~agentsdk.webconnection.PING_TIMEOUT` seconds; and a jog step a page started is cancelled (the robot holds)
when that page disconnects.

Bound to 127.0.0.1 only. There is deliberately no option to serve on another address: to
watch from another machine forward the port over SSH (``ssh -L 8080:127.0.0.1:8080 robot-pc``).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import BackendUnavailableError, ConfigurationError
from .jog import CARTESIAN_KEYS, JOG_STEP, JOINT_STEP, SHIFTED_DIGITS, JogAction, Jogger
from .webconnection import ConnectionWatch, connection_css, heartbeat_html
from .webpacing import PagePacer

if TYPE_CHECKING:
    from .robot import Robot

__all__ = ["HOST", "JOG_STEP", "JOINT_STEP", "PLOT_RATE", "PLOT_WINDOW", "RATE", "Snapshot", "WebView"]

log = logging.getLogger("agentsdk.webview")

#: the only address the page is served on
HOST = "127.0.0.1"
#: snapshots pushed to the page per second (wall time)
RATE = 30.0
#: plot redraws per second and the plotted window (s of robot time)
PLOT_RATE = 5.0
PLOT_WINDOW = 10.0


@dataclass(frozen=True)
class Snapshot:
    """What the page shows, copied on the robot's event loop in one callback."""

    stamp: float
    names: tuple[str, ...]
    position: np.ndarray
    velocity: np.ndarray
    safety: str
    cause: str
    moving_joints: int
    machine: str


def _require() -> None:
    import importlib.util

    missing = [m for m in ("viser", "yourdfpy") if importlib.util.find_spec(m) is None]
    if missing:
        raise BackendUnavailableError(
            f"the web view needs {' and '.join(missing)}; install it with `pip install 'agentsdk[web]'`"
        )


def _free_port(port: int) -> int:
    """``port`` if it can be served on 127.0.0.1 (0: any free port), else ConfigurationError."""
    import socket

    if not 0 <= port <= 65535:
        raise ConfigurationError(f"--port must be between 0 and 65535, got {port}")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        try:
            sock.bind((HOST, port))
        except OSError as exc:
            raise ConfigurationError(f"cannot serve the web view on {HOST}:{port}: {exc.strerror or exc}; "
                                     "choose another --port") from exc
        return int(sock.getsockname()[1])


class WebView:
    """The live page of one robot (see the module documentation). Use :meth:`attach`; :meth:`close` ends it."""

    def __init__(
        self,
        robot: Robot,
        port: int = 8080,
        *,
        stop_category: int | None = None,
        on_ready: Callable[[WebView], None] | None = None,
    ) -> None:
        _require()
        self.robot = robot
        self._aloop = asyncio.get_running_loop()
        self.stop_category = int(stop_category if stop_category is not None else robot.safety.config.ui_stop_category)
        self._names = tuple(robot.joint_names)
        self._machine = ""
        self._closed = threading.Event()
        self._pending: concurrent.futures.Future[Snapshot] | None = None
        self.last: Snapshot | None = None
        #: set once the page is being served (the server, the meshes and the widgets are built in the thread)
        self.ready = threading.Event()
        self._started = asyncio.Event()
        self._served = asyncio.Event()
        self._on_ready = on_ready
        self._start_wanted = threading.Event()
        self._pressed = threading.Event()
        self.error: BaseException | None = None
        self.port = _free_port(port)
        self.server: Any = None
        #: paces the frames to what the connected pages can apply (:mod:`agentsdk.webpacing`)
        self.pacer: PagePacer | None = None
        #: the pages' connections: keepalive tolerance, why each one ended (:mod:`agentsdk.webconnection`)
        self.connections: ConnectionWatch | None = None
        self._frame = 0
        #: the page (viser client id) whose jog step runs, if a page started it
        self._jog_client: int | None = None
        self._tmp = tempfile.TemporaryDirectory(prefix="agentsdk-web-")
        self._urdf: Any = None
        self._urdf_names: tuple[str, ...] = ()
        self._urdf_xml = str(getattr(robot.description, "urdf_xml", "") or "")
        self._robot_name = robot.name
        self._jogger = Jogger(robot)
        self._jog_link = self._jogger.link
        self._jogging: concurrent.futures.Future[None] | None = None
        self._jog_lock = threading.Lock()
        self._start_poses = list(robot.kinematics.link_poses().values())
        from .statemachine import StateMachine

        self._listener = StateMachine.add_transition_listener(self._on_transition)
        # building the page (importing viser, loading meshes) takes long: never on the robot's event loop
        self._thread = threading.Thread(target=self._run, name="agentsdk-webview", daemon=True)
        self._thread.start()

    @staticmethod
    def prepare() -> None:
        """Import viser and its URDF loader now (seconds of work): call before connecting, not on the robot's loop."""
        _require()
        import viser.extras  # noqa: F401
        import yourdfpy  # noqa: F401

    @classmethod
    def attach(
        cls,
        robot: Robot,
        port: int = 8080,
        *,
        stop_category: int | None = None,
        on_ready: Callable[[WebView], None] | None = None,
    ) -> WebView:
        """Serve the live page of ``robot`` on http://127.0.0.1:``port`` (call from the robot's event loop).

        The page is built in a thread; ``on_ready(view)`` is called from it once it is served.
        """
        return cls(robot, port, stop_category=stop_category, on_ready=on_ready)

    async def wait_for_start(self) -> None:
        """Show a **Start** button on the page and return once it is pressed (``agentsdk run --web --web-wait``)."""
        await self.wait_ready()
        self._start_wanted.set()
        await self._started.wait()

    async def wait_ready(self) -> None:
        """Return once the page is served (raise :class:`ConfigurationError` if it could not be)."""
        await self._served.wait()
        if self.error is not None:
            raise ConfigurationError(f"the web view could not be served: {self.error}") from self.error

    @property
    def url(self) -> str:
        """Where the page is served."""
        return f"http://{HOST}:{self.port}"

    # ------------------------------------------------------------------ page
    def _serve(self) -> None:
        """In the view's thread: start viser (its banner silenced), build the 3D scene and the widgets."""
        import rich
        import viser
        from rich.console import Console
        from viser.extras import ViserUrdf

        saved = rich._console
        rich._console = Console(quiet=True)  # viser prints a banner with rich.print; we print our own line
        try:
            self.server = viser.ViserServer(host=HOST, port=self.port, label=f"agentsdk: {self._robot_name}",
                                            verbose=False)
        finally:
            rich._console = saved
        self.port = int(self.server.get_port())
        self.pacer = PagePacer(self.server)
        self.connections = ConnectionWatch(self.server, on_disconnect=self._on_page_gone)
        self._build_gui()
        self._build_scene(ViserUrdf)

    def _build_scene(self, viser_urdf: Any) -> None:
        if not self._urdf_xml:
            self.server.gui.add_markdown("*3D view: MJCF robots are not drawn yet; the state is above.*")
            return
        import yourdfpy

        path = Path(self._tmp.name) / "robot.urdf"
        path.write_text(self._urdf_xml, encoding="utf-8")
        urdf = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=True)
        self._urdf = viser_urdf(self.server, urdf, root_node_name="/robot")
        self._urdf_names = tuple(self._urdf.get_actuated_joint_names())
        # frame the robot: its size from the link origins at the start pose
        reach = max((float(np.linalg.norm(p.position)) for p in self._start_poses), default=1.0)
        reach = max(reach, 0.2)
        self.server.scene.add_grid("/ground", width=4.0 * reach, height=4.0 * reach, cell_size=0.1)
        cam = self.server.initial_camera
        cam.position = (1.3 * reach, -1.3 * reach, 1.0 * reach)
        cam.look_at = (0.0, 0.0, 0.4 * reach)

    def _build_gui(self) -> None:
        gui = self.server.gui
        # first, so it sits at the top of the panel: the banner's style and the no-new-frame notice
        gui.add_html(connection_css())
        self._beat = gui.add_html(heartbeat_html(0))
        self._start = gui.add_button("Start", color="green", visible=False,
                                     hint="run the behavior (agentsdk run --web-wait)")

        def _press(_: Any) -> None:
            self._pressed.set()
            self._start.visible = False
            self._aloop.call_soon_threadsafe(self._started.set)

        self._start.on_click(_press)
        self._estop = gui.add_button("E-STOP", color="red", icon=None,
                                     hint=f"latch an e-stop, category {self.stop_category}")
        self._estop.on_click(lambda _: self.estop())
        self._status = gui.add_markdown("**safety:** -")
        with gui.add_folder("Recover"):
            reset = gui.add_button("Reset…", hint="clear the latched e-stop (asks first)")
            enable = gui.add_button("Enable…", hint="allow motion again (asks first)")
        reset.on_click(lambda event: self._confirm(event.client, "reset", "Clear the latched e-stop?"))
        enable.on_click(lambda event: self._confirm(event.client, "enable", "Allow the robot to move again?"))
        self._build_jog()
        self._joints = gui.add_markdown("")
        t = np.zeros(1)
        series: list[Any] = [{"label": "t (s)"}]
        series += [{"label": n, "stroke": _color(i)} for i, n in enumerate(self._names)]
        self._plot = gui.add_uplot(data=(t, *[np.zeros(1) for _ in self._names]), series=tuple(series),
                                   title="joint positions (rad)", aspect=1.5)
        self._history: deque[tuple[float, np.ndarray]] = deque()

    def _build_jog(self) -> None:
        """Jog buttons and keyboard shortcuts (:mod:`agentsdk.jog`): one step per press, the arm holds between."""
        gui = self.server.gui
        keys = {(axis, sign): key.upper() for key, (axis, sign) in CARTESIAN_KEYS.items()}
        with gui.add_folder("Jog", expand_by_default=False):
            gui.add_markdown(f"Cartesian {JOG_STEP * 100:g} cm steps of `{self._jog_link}`: keys "
                             f"{keys[0, 1.0]}/{keys[0, -1.0]} (x), {keys[1, 1.0]}/{keys[1, -1.0]} (y), "
                             f"{keys[2, 1.0]}/{keys[2, -1.0]} (z); joints: 1-9, with Shift to go back "
                             f"({JOINT_STEP:g} rad); Space stops a step")
            for axis, name in enumerate("xyz"):
                for sign in (1.0, -1.0):
                    button = gui.add_button(f"{'+' if sign > 0 else '-'}{name}")
                    button.on_click(lambda event, a=axis, s=sign: self._jog_cartesian(
                        a, s * JOG_STEP, event.client_id))
        for (axis, sign), key in keys.items():
            cmd = gui.add_command(f"Jog {'+' if sign > 0 else '-'}{'xyz'[axis]}", hotkey=key)
            cmd.on_trigger(lambda event, a=axis, s=sign: self._jog_cartesian(
                a, s * JOG_STEP, event.client_id))
        for i, name in enumerate(self._names[:9]):
            # Shift+digit: the page's hotkeys match the typed character, which Shift turns into !@#... (US layout)
            for key, modifier, sign in ((str(i + 1), None, 1.0), (SHIFTED_DIGITS[i], "shift", -1.0)):
                cmd = gui.add_command(f"Jog {name} {'+' if sign > 0 else '-'}", hotkey=key,
                                      modifier=modifier)
                cmd.on_trigger(lambda event, n=name, s=sign: self._jog_joint(
                    n, s * JOINT_STEP, event.client_id))
        stop = gui.add_command("Stop the jog", hotkey="space")
        stop.on_trigger(lambda _: self.stop_jog())

    def _on_page_gone(self, client_id: int) -> None:
        """A page disconnected: if its jog step runs, cancel it (the arm decelerates and holds)."""
        with self._jog_lock:
            if client_id != self._jog_client:
                return
            self._jog_client = None
            jogging = self._jogging
        if jogging is not None and not jogging.done():
            log.warning("web view: the page that started a jog step disconnected: the step is cancelled")
            self.stop_jog()

    def stop_jog(self) -> None:
        """Release = hold: cancel the running jog step; the arm decelerates within its limits and holds. Any thread."""
        jogging = self._jogging
        if jogging is not None and not jogging.done():
            jogging.cancel()

    def jog_cartesian(self, axis: int, step: float) -> None:
        """Move the end effector ``step`` metres along root-frame axis ``axis`` (0, 1, 2) in a straight line.

        From the desired (not measured) pose, so steps add up exactly; a press while a jog runs is
        ignored (no queue: nothing moves after the key is released). Any thread.
        """
        self._jog_cartesian(axis, step, None)

    def jog_joint(self, name: str, step: float) -> None:
        """Move joint ``name`` by ``step`` (rad or m) from its desired position, within its limits. Any thread."""
        self._jog_joint(name, step, None)

    def _jog_cartesian(self, axis: int, step: float, client_id: int | None) -> None:
        delta = np.zeros(3)
        delta[axis] = step
        self._jog(lambda: self._jogger.cartesian(delta), JogAction("cartesian", axis, float(np.sign(step))),
                  client_id)

    def _jog_joint(self, name: str, step: float, client_id: int | None) -> None:
        i = self._names.index(name)
        self._jog(lambda: self._jogger.joint(i, step), JogAction("joint", i, float(np.sign(step))), client_id)

    def _jog(self, make: Callable[[], Any], action: JogAction, client_id: int | None) -> None:
        """Start a step unless one runs; ``client_id``: the page that asked (its disconnect cancels the step)."""
        with self._jog_lock:
            if self._jogging is not None and not self._jogging.done():
                return
            self._jog_client = client_id
            self._jogging = asyncio.run_coroutine_threadsafe(self._guarded_jog(make, action), self._aloop)

    async def _guarded_jog(self, make: Callable[[], Any], action: JogAction) -> None:
        try:
            result = await make()
        except Exception as exc:  # a refused jog (e-stop latched, out of reach) is logged, never raised
            log.warning("web view: jog %s failed: %s", action.describe(self._names), exc)
            return
        if not result.ok:
            log.warning("web view: jog %s refused: %s", action.describe(self._names), result.message)

    def _confirm(self, client: Any, action: str, question: str) -> None:
        if client is None:
            return
        with client.gui.add_modal(f"{action.capitalize()} the robot") as modal:
            client.gui.add_markdown(question)
            yes = client.gui.add_button(f"Yes, {action}", color="orange")
            no = client.gui.add_button("Cancel")

            def _yes(_: Any) -> None:
                modal.close()
                self.request(action)

            yes.on_click(_yes)
            no.on_click(lambda _: modal.close())

    # --------------------------------------------------------------- actions
    def estop(self) -> None:
        """What the E-STOP button does: latch an e-stop of :attr:`stop_category` (any thread)."""
        log.warning("web view: e-stop (category %d) requested", self.stop_category)
        try:
            self.robot.estop_threadsafe(self.stop_category)
        except Exception:  # the robot may be closing: the page must not crash
            log.exception("web view: e-stop failed")

    def request(self, action: str) -> None:
        """Run ``robot.reset()`` or ``robot.enable()`` on the robot's loop (after the page's confirmation)."""
        call = {"reset": self.robot.reset, "enable": self.robot.enable}[action]
        fut = asyncio.run_coroutine_threadsafe(call(), self._aloop)

        def _done(f: concurrent.futures.Future[None]) -> None:
            exc = f.exception() if not f.cancelled() else None
            if exc is not None:
                log.warning("web view: %s failed: %s", action, exc)

        fut.add_done_callback(_done)

    def _on_transition(self, machine: Any, record: Any) -> None:
        if getattr(machine, "robot", None) is not self.robot:
            return
        root = machine
        while root.parent is not None:
            root = root.parent
        self._machine = f"{type(root).__name__}: {root.state_path or '(finished)'}"

    # ------------------------------------------------------------ publishing
    def _snapshot(self) -> Snapshot:
        """On the robot's loop: copy what the page shows (a few small arrays)."""
        robot = self.robot
        st = robot.latest_state()
        safety = robot.safety
        state = safety.state.name
        cause = safety.latch_cause() if state in ("ESTOP", "FAULT") else ""
        moving = int(np.count_nonzero(safety.motions.owned_mask))
        return Snapshot(float(st.stamp), self._names, np.array(st.position, dtype=float),
                        np.array(st.velocity, dtype=float), state, cause, moving, self._machine)

    def _take(self) -> Snapshot | None:
        pending = self._pending
        if pending is not None and not pending.done():
            return None  # the loop is busy: skip this frame rather than queue up work for it
        if self._aloop.is_closed() or self.robot.closed:
            return None

        async def _grab() -> Snapshot:
            return self._snapshot()

        self._pending = fut = asyncio.run_coroutine_threadsafe(_grab(), self._aloop)
        try:
            return fut.result(timeout=0.5)
        except (concurrent.futures.TimeoutError, concurrent.futures.CancelledError):
            return None
        except Exception:  # the robot closed between the check and the call
            log.debug("web view: snapshot failed", exc_info=True)
            return None

    def _run(self) -> None:
        try:
            self._serve()
        except Exception as exc:
            self.error = exc
            log.error("web view: cannot serve the page: %s", exc)
            return
        finally:
            self.ready.set()
            with contextlib.suppress(RuntimeError):  # (the robot's loop may be gone already)
                self._aloop.call_soon_threadsafe(self._served.set)
        if self._on_ready is not None:
            self._on_ready(self)
        pacer = self.pacer
        assert pacer is not None  # (made by _serve)
        period, next_plot, delay = 1.0 / RATE, 0.0, 1.0 / RATE
        while not self._closed.wait(delay):
            began = time.monotonic()
            delay = period
            snap = self._take()
            if snap is None:
                continue
            try:
                self._publish(snap)
                now = time.monotonic()
                if now >= next_plot:
                    next_plot = now + 1.0 / PLOT_RATE
                    self._publish_plot()
                # no frame for a page that has not applied the last one (a flooded page stops answering clicks)
                round_trip = pacer.sync(self._closed)
                delay = pacer.next_delay(period, time.monotonic() - began, round_trip)
            except Exception:  # a disconnecting browser must not end the view
                log.debug("web view: publishing failed", exc_info=True)

    def _publish(self, snap: Snapshot) -> None:
        self.last = snap
        if self._start_wanted.is_set() and not self._pressed.is_set() and not self._start.visible:
            self._start.visible = True
        if self._urdf is not None:
            pos = dict(zip(snap.names, snap.position.tolist(), strict=True))
            self._urdf.update_cfg(np.array([pos.get(n, 0.0) for n in self._urdf_names]))
        speed = float(np.max(np.abs(snap.velocity))) if len(snap.velocity) else 0.0
        motion = (f"following a motion on {snap.moving_joints} joint(s)" if snap.moving_joints
                  else ("at rest" if speed < self.robot.safety.config.rest_velocity else "moving"))
        lines = [f"**safety:** `{snap.safety}`" + (f" — {snap.cause}" if snap.cause else ""),
                 f"**motion:** {motion} (max speed {speed:.3f})",
                 f"**state machine:** {snap.machine or '(none)'}",
                 f"**time:** {snap.stamp:.3f} s"]
        self._set_content(self._status, "  \n".join(lines))
        self._frame += 1
        self._beat.content = heartbeat_html(self._frame)  # (a new frame restarts the page's stale timer)
        rows = "\n".join(f"| {n} | {q:+.4f} | {v:+.4f} |" for n, q, v in zip(snap.names, snap.position,
                                                                              snap.velocity, strict=True))
        self._set_content(self._joints, "| joint | position | velocity |\n|---|---|---|\n" + rows)
        self._history.append((snap.stamp, snap.position))
        while self._history and self._history[0][0] < snap.stamp - PLOT_WINDOW:
            self._history.popleft()

    @staticmethod
    def _set_content(markdown: Any, text: str) -> None:
        if markdown.content != text:  # (an unchanged text is not sent again)
            markdown.content = text

    def _publish_plot(self) -> None:
        if len(self._history) < 2:
            return
        t = np.array([h[0] for h in self._history])
        q = np.array([h[1] for h in self._history])
        self._plot.data = (t, *[q[:, i].copy() for i in range(q.shape[1])])

    # ------------------------------------------------------------------ close
    def close(self) -> None:
        """Stop publishing and serving. Idempotent."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._listener.remove()
        self._thread.join(timeout=30.0)
        if self.connections is not None:
            self.connections.close()
        try:
            if self.server is not None:
                import rich
                from rich.console import Console

                saved = rich._console
                rich._console = Console(quiet=True)  # viser's "Server stopped"
                try:
                    self.server.stop()
                finally:
                    rich._console = saved
        finally:
            self._tmp.cleanup()


_PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
            "#17becf")


def _color(i: int) -> str:
    return _PALETTE[i % len(_PALETTE)]
