"""Issue 24: a floating robot whose light links carry heavy rotors (MJCF ``armature``) stands on PyBullet.

PyBullet simulates no rotor inertia; the backend's floating step adds it in its own solve and measures
the contact forces PyBullet applied from the motion PyBullet produced. Measured with the rotors' inertia
(which PyBullet's bodies never had), the rotors' ``A qacc`` came back as a contact force with the gain
``-A / M_rigid``: Menagerie's Apollo (0.12 kg ankle links on 0.12 kg·m² rotors) diverged 8 ms in. Here
the quadruped fixture's shins get rotors about 15 and 20 times their own inertia about the knee (Apollo's ankles:
12; before, a ratio above about 6 diverged, and with the estimate low-passed the knees swung 0.02-0.1 rad).
"""

from __future__ import annotations

from pathlib import Path

import pytest

import agentsdk

pytestmark = pytest.mark.timeout(300)

QUADRUPED = Path(__file__).parent / "fixtures" / "mjcf_quadruped" / "quadruped.xml"


@pytest.mark.parametrize("armature", ["0.04", "0.05"])
async def test_light_links_on_heavy_rotors_stand_in_contact(tmp_path: Path, armature: str) -> None:
    xml = QUADRUPED.read_text()
    assert xml.count('range="-2.4 -0.2"/>') == 4
    path = tmp_path / "quadruped.xml"
    path.write_text(xml.replace('range="-2.4 -0.2"/>', f'range="-2.4 -0.2" armature="{armature}"/>'))
    async with agentsdk.connect("pybullet", robot=path) as robot:
        assert robot.backend.floating_base
        z0 = float(robot.base_state().pose.position[2])
        q0 = (await robot.read()).position.copy()
        for _ in range(8):
            await robot.clock.sleep(0.25)
            z = float(robot.base_state().pose.position[2])
            assert abs(z - z0) < 0.05 * z0, f"base at {z:.3f} m, started at {z0:.3f} m"
        # the fixture's soft servos (kp 60) hold the legs 0.03 rad off under the load, as on MuJoCo
        assert abs((await robot.read()).position - q0).max() < 0.04
