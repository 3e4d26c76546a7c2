"""``agentsdk serve --web``: the ROS 2 face and the live page of the same robot, the page on loopback only."""

from __future__ import annotations

import importlib.util
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest
from ros_domains import random_domain

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [
    pytest.mark.timeout(300),
    pytest.mark.skipif(importlib.util.find_spec("viser") is None, reason="needs agentsdk[web] (viser)"),
    pytest.mark.skipif(importlib.util.find_spec("cyclonedds") is None, reason="needs agentsdk[ros2] (cyclonedds)"),
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def listening_addresses(port: int) -> set[str]:
    """The local addresses of the TCP sockets listening on ``port`` (Linux /proc/net/tcp and tcp6), as hex."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not os.path.exists(table):
            continue
        with open(table) as f:
            next(f)
            for line in f:
                local, state = line.split()[1], line.split()[3]
                address, hexport = local.split(":")
                if state == "0A" and int(hexport, 16) == port:  # 0A: LISTEN
                    found.add(address)
    return found


def test_serve_web_serves_the_page_on_loopback_only() -> None:
    port = _free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "agentsdk", "serve", "--robot", "arm3", "--backend", "mock", "--web", "--port",
         str(port), "--domain-id", str(random_domain())],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    err: list[str] = []
    reader = threading.Thread(target=lambda: err.extend(iter(proc.stderr.readline, "")), daemon=True)  # type: ignore[union-attr]
    reader.start()
    try:
        deadline = time.monotonic() + 240
        while not (any("serving arm3" in x for x in err) and any("web view:" in x for x in err)):
            assert proc.poll() is None, "".join(err)
            assert time.monotonic() < deadline, "".join(err)
            time.sleep(0.1)
        assert any(f"web view: http://127.0.0.1:{port}" in x for x in err), "".join(err)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=60) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
        # bound to 127.0.0.1 and nothing else (no flag exposes it elsewhere)
        assert listening_addresses(port) == {"0100007F"}, listening_addresses(port)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
        reader.join(timeout=10)
        if not reader.is_alive():  # never close a pipe under a thread still reading it
            for stream in (proc.stdout, proc.stderr):
                if stream is not None:
                    stream.close()
    assert code == 130, "".join(err)
    assert not any("Traceback" in x for x in err), "".join(err)
