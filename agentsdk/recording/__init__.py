"""Record runs to MCAP, read them back, and replay their commands into a fresh connection.

    agentsdk run behaviors/wave.py --record run.mcap        # record
    agentsdk replay run.mcap --backend mujoco               # replay + divergence report

Channels (ROS 2 CDR messages, ``ros2msg`` schemas, zstd-compressed chunks)
--------------------------------------------------------------------------

=========================  ===================================  ==============================================
topic                      message type                         content
=========================  ===================================  ==============================================
``/joint_states``          ``sensor_msgs/msg/JointState``       measured state, decimated to ``rate`` Hz of
                                                                robot time (default :data:`STATE_RATE`;
                                                                ``None``: every control tick)
``/joint_commands``        ``agentsdk_msgs/msg/JointCommand``   the servo setpoint actually written to the
                                                                backend (after the safety layer): name[],
                                                                position[], velocity[], acceleration[] (fed
                                                                forward by the inverse-dynamics term),
                                                                effort[], mode[] (uint8: 0 position, 1
                                                                velocity, 2 effort), enabled[], kp[], kd[],
                                                                target[] (the last commanded value before
                                                                ramping)
``/safety/events``         ``agentsdk_msgs/msg/SafetyEvent``    kind, joint ("" for none), detail
``/behavior/transitions``  ``agentsdk_msgs/msg/Transition``     state-machine history records: machine,
                                                                source, target, event ("" for none), note
``/tf``                    ``tf2_msgs/msg/TFMessage``           every link's parent -> child transform from
                                                                forward kinematics, at ``tf_rate`` Hz
``/robot_description``     ``std_msgs/msg/String``              the URDF, once, at the start
``/sensors/<name>``        the sensor's ROS message (below)     every sensor but cameras, at most
                                                                ``sensor_rate`` Hz (default
                                                                :data:`SENSOR_RATE`); header stamp: when
                                                                it was measured, frame_id: its link
=========================  ===================================  ==============================================

Sensor message types: ``sensor_msgs/msg/Imu``, ``geometry_msgs/msg/WrenchStamped``
(force-torque), ``geometry_msgs/msg/Vector3Stamped`` (accelerometer, gyro, force, torque),
``geometry_msgs/msg/QuaternionStamped`` (orientation), ``sensor_msgs/msg/Range``,
``sensor_msgs/msg/LaserScan``, ``agentsdk_msgs/msg/Contact`` and
``agentsdk_msgs/msg/JointSensor`` (joint sensors, temperature).  A sensor slower
than ``sensor_rate`` has each sample written once.  :func:`read_recording`
returns them as ``RunData.sensors[name]`` (:class:`SensorSeries`).  A robot
without sensors records exactly as before.

Cameras (once started) go to ``/sensors/<camera>`` as
``sensor_msgs/msg/CompressedImage`` (PNG, or JPEG) at ``camera_rate`` Hz
(default :data:`CAMERA_RATE`; 0 for none): the tick copies a new frame into a
preallocated frame pool, the writer thread compresses it.  ``RunData.images[name]``
(:class:`ImageSeries`) holds the compressed frames.  Depth images are not recorded.

The file is a rosbag2 MCAP (profile ``ros2``, the ``rosbag2`` metadata
record): Foxglove decodes every channel from its embedded ``ros2msg`` schema
(the ``agentsdk_msgs`` definitions included), ``rosbags`` reads it with the
definitions registered from the schemas.  A metadata record named ``agentsdk``
holds what replay needs: the robot (name, or absolute path of its
robot.yaml/URDF), the backend and its options, the control period, the joint
names, the record rates, the validated robot.yaml content and the behavior
script.  ``--record-format ros2`` (``format="ros2"``) writes only standard
message types (``/joint_commands`` as ``sensor_msgs/msg/JointState``, no
events or transitions) for ``ros2 bag play``; such a file cannot be replayed.
Recordings of earlier versions (JSON messages, format ``agentsdk-recording/1``;
CDR commands without ``acceleration[]``, format ``agentsdk-recording/2``) are
still read; their ``RunData.cmd_acceleration`` is ``None``.

Why CDR and ``ros2msg`` rather than protobuf: the per-tick messages have a
fixed layout for a given robot, so a block of them is encoded (and decoded)
as one numpy array, with no Python work per message; CDR with ``ros2msg``
schemas is what both Foxglove and ROS 2 tooling read without extra schema
files, and it unifies the default format with the rosbag2 variant.

Size: the joint states are decimated by default (50 Hz) because at 500 Hz
they alone would exceed 2 MB per minute of robot time (nine float64 a tick are
nearly incompressible).  Commands are never decimated, so a recording replays
exactly.  A moving 3-joint arm costs about 1.5-2 MB per minute of robot time.

Timing
------
Log time (and ``header.stamp``) is robot clock time in nanoseconds: simulated
time in lockstep, time since connect in real time.  A ``/joint_states``
message stamped ``t`` is the state measured at the end of the tick that
started at ``t - period``; the ``/joint_commands`` message applied during that
tick is stamped ``t - period`` (when it was written).

``/joint_commands`` is change-based: a message is written at every tick whose
setpoint differs from the previous tick's, at the tick just before each change
(so a line plot shows holds as flat segments) and at the run's last tick;
sample-and-hold reconstructs the setpoint of every tick exactly.

Cost on the control loop
------------------------
The recorder's tick hook copies a few numpy rows into a preallocated block
(about 3 µs per tick for a 3-joint arm); no encoding and no Python object per
tick.  A full block (or, every :data:`FLUSH_INTERVAL` s, a partial one: of wall
time on a realtime robot, of robot time in lockstep) is handed to a writer
thread, which selects the rows, computes ``/tf``, encodes the block's messages
and lays out its MCAP chunk with numpy (no Python work per message: the
``mcap`` package's writer spent about 8 µs of interpreter time per message, in
the GIL the control loop needs), compresses it with zstd and writes it.  Blocks
come from a fixed pool: if the writer ever falls behind by the whole pool,
ticks are dropped (counted in :attr:`Recorder.dropped_ticks`, logged) rather
than the loop blocked or memory grown.  :meth:`Recorder.finish` joins the
thread: call it after the robot is closed, as the CLI does.

With block lockstep (:meth:`agentsdk.Robot.block_lockstep`) the hook takes a
block of ticks at once (it is a :class:`agentsdk.block.BlockObserver`): one
copy of the block's rows, cut where the per-tick hook would hand a block to the
writer, so a recorded run keeps its blocks and its file is byte for byte the
one written tick by tick.  A robot with recorded sensors or cameras records
tick by tick (their samples exist only in the tick).

Crash safety
------------
Every hand-off closes an MCAP chunk and pushes it to the OS, so a killed run
loses at most about half a second (of robot time in lockstep: more wall time
where the simulation runs slower than real time); :func:`read_recording` reads
such a file up to its last complete chunk and sets ``RunData.truncated``.

Determinism
-----------
In lockstep, where a chunk ends depends on the ticks alone (the pool's size, the
flush in robot time, the camera frames), not on the machine's speed: two runs of
the same behavior, tick by tick or in blocks, write the same bytes, given the
same ``created`` metadata (the wall-clock date, which ``metadata=`` overrides).

Reading
-------
:func:`read_recording` streams the file one chunk at a time into arrays
allocated once from the file's message counts (the summary, or a counting pass
for a truncated file), decoding each chunk's messages as one array: memory is
the returned arrays plus one chunk.

State-machine transitions
-------------------------
The recorder registers a transition listener
(:meth:`StateMachine.add_transition_listener <agentsdk.statemachine.StateMachine.add_transition_listener>`)
while it is attached, and keeps the records of machines whose ``robot`` is the
recorded robot.

Replay
------
:func:`replay` connects a fresh robot (lockstep for simulators), and an
updater writes the recorded setpoint (position, velocity, acceleration, effort,
kp, kd, enabled, mode) into the robot's setpoint (a COMMAND-phase tick hook) at the same tick it was
applied in the recording.  The safety layer filters it again, which leaves it
unchanged (the recorded setpoint is already limited and ramped); the command
watchdog is turned off because no commands are sent.  Lockstep MuJoCo is
deterministic, so a MuJoCo recording replays into MuJoCo bit for bit.

A recording without the setpoint's acceleration (format ``agentsdk-recording/2``,
written before the servo law fed the desired motion's inverse dynamics forward)
replays with the acceleration estimated from the recorded velocity setpoints
(central differences over consecutive ticks): close, no longer bit for bit.
:attr:`ReplayResult.notes` says so, and a warning is logged.
"""

from . import _recorder
from ._cdr import MSGDEFS as MSGDEFS
from ._channels import CDR2_FORMAT as CDR2_FORMAT
from ._channels import FORMAT, TOPICS, robot_spec_for_metadata
from ._channels import JOINT_COMMANDS as JOINT_COMMANDS
from ._channels import JOINT_STATES as JOINT_STATES
from ._channels import JSON_FORMAT as JSON_FORMAT
from ._channels import METADATA_NAME as METADATA_NAME
from ._channels import ROBOT_DESCRIPTION as ROBOT_DESCRIPTION
from ._channels import SAFETY_EVENTS as SAFETY_EVENTS
from ._channels import TF as TF
from ._channels import TRANSITIONS as TRANSITIONS
from ._images import ImageSeries
from ._reader import RunData, read_recording
from ._recorder import BLOCK_TICKS, Recorder
from ._recorder import FLUSH_INTERVAL as FLUSH_INTERVAL
from ._recorder import RECORDER_ORDER as RECORDER_ORDER
from ._replay import ReplayResult, replay
from ._sensors import SensorSeries

# re-bound here with their documentation, which Sphinx reads from the assignments in this module
#: default rate of /joint_states (Hz of robot time); commands are never decimated
STATE_RATE = _recorder.STATE_RATE
#: default rate of /tf (Hz of robot time): smooth in Foxglove, cheap for a 30-link robot
TF_RATE = _recorder.TF_RATE
#: ``--record-format`` choices
RECORD_FORMATS = _recorder.RECORD_FORMATS
#: default rate of the camera topics (Hz of robot time)
CAMERA_RATE = _recorder.CAMERA_RATE
#: default rate of the ``/sensors/<name>`` topics (Hz of robot time); a slower sensor: each of its samples
SENSOR_RATE = _recorder.SENSOR_RATE

__all__ = [
    "BLOCK_TICKS",
    "CAMERA_RATE",
    "FORMAT",
    "RECORD_FORMATS",
    "SENSOR_RATE",
    "STATE_RATE",
    "TF_RATE",
    "TOPICS",
    "ImageSeries",
    "Recorder",
    "ReplayResult",
    "RunData",
    "SensorSeries",
    "read_recording",
    "replay",
    "robot_spec_for_metadata",
]

for _name in __all__:
    _obj = globals()[_name]
    if getattr(_obj, "__module__", "").startswith(__name__ + "."):
        _obj.__module__ = __name__  # documented and pickled as agentsdk.recording.X
