"""Issue 23 item 4 / acceptance 4: only who belongs gets in (``agentsdk.ros2.security``).

The robot is served with a keystore (operator and viewer roles, Cyclone DDS domain tags); each
client is its own process (``tests/ros2_peers/identity_client.py``: one DDS configuration per
domain and process) on loopback, and reports the topics it discovered, the joint_states it got
and the replies to its goals. Measured: a participant without a tag (on either role's domain)
sees no topic of the robot and moves nothing; a viewer reads joint_states but its goals and
trajectories reach nothing; an operator's goal is accepted and moves the robot.
"""

from __future__ import annotations

import asyncio
import json
import os
import stat
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

import agentsdk
from agentsdk import ConfigurationError, InvalidValueError
from agentsdk.ros2.security import (
    create_keystore,
    expose_secured,
    identity_config,
    load_identity,
    load_keystore,
)

pytestmark = pytest.mark.timeout(240)
CLIENT = Path(__file__).parent / "ros2_peers" / "identity_client.py"
ROOT = Path(__file__).resolve().parent.parent


def test_keystore_files_roles_and_secrets(tmp_path: Path) -> None:
    store = tmp_path / "keys"
    ids = create_keystore(store, domain_id=41)
    assert (ids["operator"].domain_id, ids["viewer"].domain_id) == (41, 42)
    assert ids["operator"].tag != ids["viewer"].tag and len(ids["viewer"].tag) == 64
    assert load_keystore(store) == ids
    assert load_identity(store / "viewer.json") == ids["viewer"]
    viewer_file = json.loads((store / "viewer.json").read_text())
    assert ids["operator"].tag not in json.dumps(viewer_file)  # a viewer's file holds nothing of the operator's
    for f in ("keystore.json", "operator.json", "viewer.json"):
        assert stat.S_IMODE((store / f).stat().st_mode) == 0o600
    assert stat.S_IMODE(store.stat().st_mode) == 0o700
    with pytest.raises(ConfigurationError, match="exists"):
        create_keystore(store, domain_id=41)
    again = create_keystore(store, domain_id=41, overwrite=True)
    assert again["operator"].tag != ids["operator"].tag
    with pytest.raises(InvalidValueError, match="differ"):
        create_keystore(tmp_path / "k2", domain_id=5, viewer_domain_id=5)
    (tmp_path / "bad.json").write_text('{"format": "agentsdk-keystore/1", "mechanism": "cyclonedds-domain-tag"}')
    with pytest.raises(ConfigurationError, match="identity"):
        load_identity(tmp_path / "bad.json")
    with pytest.raises(ConfigurationError, match="no such"):
        load_keystore(tmp_path / "nowhere")
    xml = identity_config(ids["viewer"], "10.1.2.3", ["10.1.2.4"])
    assert f"<Tag>{again['viewer'].tag}</Tag>" not in xml and f"<Tag>{ids['viewer'].tag}</Tag>" in xml
    assert '<Domain id="42">' in xml and '<Peer Address="10.1.2.4"/>' in xml


async def _client(tmp_path: Path, domain: int, config: str | None, joint: int, target: float,
                  seconds: float) -> dict[str, Any]:
    cfg = "-"
    if config is not None:
        path = tmp_path / f"cfg-{domain}-{joint}.xml"
        path.write_text(config)
        cfg = str(path)
    env = {k: v for k, v in os.environ.items() if k not in ("CYCLONEDDS_URI", "ROS_DOMAIN_ID")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
    proc = await asyncio.create_subprocess_exec(
        sys.executable, str(CLIENT), str(domain), cfg, "/sec", str(seconds), str(joint), str(target),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=env)
    out, err = await asyncio.wait_for(proc.communicate(), 120)
    assert proc.returncode == 0, err.decode()
    result: dict[str, Any] = json.loads(out.decode().strip().splitlines()[-1])
    return result


def _robot_topics(topics: list[str]) -> list[str]:
    return [t for t in topics if "/sec/" in t or t.endswith("sec")]


async def test_unknown_viewer_and_operator_get_what_their_role_allows(tmp_path: Path) -> None:
    base = 30 + 2 * (os.getpid() % 90)
    ids = create_keystore(tmp_path / "keys", domain_id=base)
    op, viewer = ids["operator"], ids["viewer"]
    async with agentsdk.connect("mock", robot="arm3", realtime=True, safety={"stall_timeout": 5.0}) as robot:
        async with expose_secured(robot, tmp_path / "keys", "/sec"):
            start = np.array(robot.latest_state().position)
            # no tag, on the operator's and on the viewer's domain: nothing seen, nothing moved
            for domain in (op.domain_id, viewer.domain_id):
                unknown = await _client(tmp_path, domain, None, 0, 0.4, 5.0)
                assert _robot_topics(unknown["topics"]) == [] and unknown["joint_states"] == 0, unknown
                assert unknown["goal_replies"] == [], unknown
                np.testing.assert_allclose(robot.latest_state().position, start, atol=1e-9)
            # a wrong tag (the viewer's) on the operator's domain: the same
            wrong = await _client(tmp_path, op.domain_id, identity_config(viewer).replace(
                f'id="{viewer.domain_id}"', f'id="{op.domain_id}"'), 0, 0.4, 4.0)
            assert _robot_topics(wrong["topics"]) == [] and wrong["joint_states"] == 0, wrong
            # the viewer: reads joint_states, its goals and trajectories reach nothing
            seen = await _client(tmp_path, viewer.domain_id, identity_config(viewer), 1, 0.4, 5.0)
            assert seen["joint_states"] > 0 and "rt/sec/joint_states" in seen["topics"], seen
            assert not any("send_goal" in t or "joint_trajectory" in t.split("/")[-1] for t in seen["topics"])
            assert seen["goal_replies"] == [], seen
            await asyncio.sleep(0.5)
            np.testing.assert_allclose(robot.latest_state().position, start, atol=1e-9)
            # the operator: the goal is accepted and the robot moves
            ok = await _client(tmp_path, op.domain_id, identity_config(op), 2, 0.4, 30.0)
            assert ok["goal_replies"] and ok["goal_replies"][0], ok
            async with asyncio.timeout(20):
                while abs(robot.latest_state().position[2] - 0.4) > 1e-3 or robot.busy:  # noqa: ASYNC110
                    await asyncio.sleep(0.05)


def test_security_command_creates_and_prints_identities(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from agentsdk.ros2.cli import security_main

    assert security_main(["create", str(tmp_path / "ks"), "--domain-id", "20", "--viewer-domain-id", "25"]) == 0
    assert "viewer.json (domain 25)" in capsys.readouterr().out
    assert security_main(["create", str(tmp_path / "ks")]) != 0  # kept unless --force
    assert "exists" in capsys.readouterr().err
    assert security_main(["config", str(tmp_path / "ks" / "viewer.json"), "--interface", "10.9.0.2",
                          "--peer", "10.9.0.1"]) == 0
    xml = capsys.readouterr().out
    assert '<Domain id="25">' in xml and load_identity(tmp_path / "ks" / "viewer.json").tag in xml
    assert security_main(["config", str(tmp_path / "ks" / "viewer.json"), "--interface", "10.9.0.2;rm"]) != 0
    assert "interface" in capsys.readouterr().err


def test_serve_refuses_conflicting_network_options(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    from agentsdk.ros2.cli import main

    create_keystore(tmp_path / "ks", domain_id=3)
    assert main(["--backend", "mock", "--keystore", str(tmp_path / "ks"), "--domain-id", "3"]) != 0
    assert "--keystore sets the domains" in capsys.readouterr().err
    assert main(["--backend", "mock", "--keystore", str(tmp_path / "missing")]) != 0
    assert "no such keystore" in capsys.readouterr().err
    assert main(["--backend", "mock", "--interface", "eth0 10.0.0.1"]) != 0
    assert "interface" in capsys.readouterr().err
    monkeypatch.setenv("CYCLONEDDS_URI", "<CycloneDDS/>")
    assert main(["--backend", "mock", "--interface", "10.0.0.1"]) != 0
    assert "not both" in capsys.readouterr().err
