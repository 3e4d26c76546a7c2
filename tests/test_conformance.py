"""The conformance kit on every registered backend, on a tiny in-suite backend, and proof it can fail."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from tiny_backend import TinyController

import agentsdk
from agentsdk.backends.can.testing import EmulatedCanConformance
from agentsdk.backends.ros2.testing import ServedRos2Conformance
from agentsdk.registry import available_backends
from agentsdk.testing import BackendConformance, SensorConformance

# runs alone, not beside another test worker: realtime timing (see the 'serial' marker in pyproject.toml)
pytestmark = pytest.mark.serial

pytest_plugins = ["pytester"]

#: backends that need a fixture around them (hardware -> emulator)
FIXTURES: dict[str, type[BackendConformance]] = {"can": EmulatedCanConformance, "ros2": ServedRos2Conformance}

for _name in available_backends():
    _base = FIXTURES.get(_name, BackendConformance)
    globals()[f"TestConformance_{_name}"] = type(f"TestConformance_{_name}", (_base,), {"backend": _name})


def test_every_registered_backend_has_a_conformance_run() -> None:
    names = set(available_backends())
    assert {"mock", "mujoco", "pybullet", "can"} <= names
    for name in names:
        assert f"TestConformance_{name}" in globals()


@pytest.fixture
def tiny_registered() -> Any:
    agentsdk.register_backend("tiny", TinyController)
    yield
    agentsdk.unregister_backend("tiny")


@pytest.mark.usefixtures("tiny_registered")
class TestTinyBackend(BackendConformance):
    backend = "tiny"
    robot = "arm3"


# -------------------------------------------------- the kit must be able to fail
BROKEN = '''
import threading
import numpy as np
import agentsdk
from agentsdk.testing import BackendConformance, SensorConformance
from tiny_backend import TinyController


class IgnoresVelocity(TinyController):
    name = "ignores_velocity"

    def _write(self, sp):
        super()._write(sp)
        self.sp["velocity"][:] = 0.0
        self.sp["kd"][self.sp["kp"] == 0] = 0.0   # velocity commands do nothing


class LeaksAfterClose(TinyController):
    name = "leaks"

    async def _open(self):
        await super()._open()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._stop.wait, name="leaky-poller", daemon=True)
        self._thread.start()

    async def _close(self):
        pass          # forgets to stop its thread


class IgnoresTorqueOff(TinyController):
    name = "ignores_torque_off"

    def _write(self, sp):
        super()._write(sp)
        self.on[:] = True             # keeps driving after an e-stop

    def _emergency_stop(self, category):
        pass


agentsdk.register_backend("ignores_velocity", IgnoresVelocity)
agentsdk.register_backend("leaks", LeaksAfterClose)
agentsdk.register_backend("ignores_torque_off", IgnoresTorqueOff)


class TestIgnoresVelocity(BackendConformance):
    backend = "ignores_velocity"
    settle_time = 0.5


class TestLeaks(BackendConformance):
    backend = "leaks"


class TestIgnoresTorqueOff(BackendConformance):
    backend = "ignores_torque_off"
'''


def test_kit_fails_broken_backends(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(tiny_backend=(Path(__file__).parent / "tiny_backend.py").read_text())
    pytester.makepyfile(test_broken=BROKEN)
    pytester.makeini("[pytest]\nasyncio_mode = auto\nasyncio_default_fixture_loop_scope = function\n")
    result = pytester.runpytest_subprocess("test_broken.py", "-q", "-p", "no:cacheprovider")
    outcomes = result.parseoutcomes()
    assert outcomes.get("failed", 0) == 4, result.stdout.str()
    result.stdout.fnmatch_lines_random([
        "*FAILED test_broken.py::TestIgnoresVelocity::test_velocity_mode_reaches_target*",
        "*FAILED test_broken.py::TestLeaks::test_close_is_idempotent_and_later_calls_raise*",
        "*FAILED test_broken.py::TestIgnoresTorqueOff::test_threadsafe_estop_removes_torque_within_one_tick*",
        "*FAILED test_broken.py::TestIgnoresTorqueOff::test_loop_stall_is_detected_and_removes_torque*",
    ])


# -------------------------------------------------- sensors (issue 25)
_SENSOR_ARM = str(Path(__file__).parent / "fixtures" / "sensor_arm" / "nocam.yaml")
_SERVED = {
    "mock": ("lift_position",),
    "mujoco": ("wrist_ft", "tool_contact", "carriage_imu", "lift_position", "height"),
    "pybullet": ("wrist_ft", "tool_contact", "carriage_imu", "lift_position", "height"),
}
for _name, _expected in _SERVED.items():
    globals()[f"TestSensorConformance_{_name}"] = type(
        f"TestSensorConformance_{_name}", (SensorConformance,),
        {"backend": _name, "robot": _SENSOR_ARM, "expected_sensors": _expected,
         "connect_options": {"safety": {"stall_timeout": 5.0}}},
    )


class _NanImu(TinyController):
    """Serves an IMU but writes NaN into it: the sensor clause must fail."""

    name = "nan_imu"
    sensor_kinds = frozenset({"imu"})

    def _read_sensors(self, channels: Any) -> None:
        for ch in channels:
            if ch.due:
                ch.values[:] = np.nan


def _arm3_with_imu(tmp_path: Path) -> Path:
    import yaml

    src = Path(__file__).resolve().parents[1] / "robots" / "arm3"
    cfg = yaml.safe_load((src / "robot.yaml").read_text())
    cfg["description"] = str(src / cfg["description"])
    cfg["sensors"] = [{"name": "imu", "type": "imu", "link": "link1"}]
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


async def test_sensor_kit_fails_a_backend_that_writes_nan(tmp_path: Path) -> None:
    path = _arm3_with_imu(tmp_path)
    agentsdk.register_backend("nan_imu", _NanImu)
    try:
        kit = type("K", (SensorConformance,), {"backend": "nan_imu", "robot": str(path),
                                              "expected_sensors": ("imu",)})()
        with pytest.raises(AssertionError, match="imu"):
            await kit.test_sensors_read_well_formed_values()
    finally:
        agentsdk.unregister_backend("nan_imu")
