"""Record runs to MCAP, read them back, and replay their commands into a fresh connection.

    agentsdk run behaviors/wave.py --record run.mcap        # record
    agentsdk replay run.mcap --backend mujoco               # replay + divergence report

Channels (all ``jsonschema`` schemas, ``json`` message encoding)
----------------------------------------------------------------

=========================  ==============================  ==================================================
topic                      schema name                     content
=========================  ==============================  ==================================================
``/joint_states``          ``sensor_msgs/msg/JointState``  measured state after every control tick (or
                                                           decimated to ``record_rate`` Hz): ``header.stamp``
                                                           {sec, nanosec}, ``name[]``, ``position[]``,
                                                           ``velocity[]``, ``effort[]``
``/joint_commands``        ``agentsdk/msg/JointCommand``   the servo setpoint actually written to the backend
                                                           (after the safety layer): the JointState fields
                                                           (desired position/velocity/effort) plus ``mode[]``
                                                           ("position"/"velocity"/"effort"), ``enabled[]``
                                                           ``kp[]``, ``kd[]`` and ``target[]`` (the last
                                                           commanded value before ramping)
``/safety/events``         ``agentsdk/msg/SafetyEvent``    ``kind``, ``joint`` (or null), ``detail``
``/behavior/transitions``  ``agentsdk/msg/Transition``     state-machine history records: ``machine``,
                                                           ``source``, ``target``, ``event``, ``note``
=========================  ==============================  ==================================================

A metadata record named ``agentsdk`` holds what replay needs: the robot (name,
or absolute path of its robot.yaml/URDF), the backend and its options, the
control period, the joint names, the validated robot.yaml content and the
behavior script.

Why JSON and not ROS 2 CDR: Foxglove decodes ``json`` channels natively from
their JSON schema (plots of ``/joint_states.position[0]`` and
``/joint_commands.position[0]`` work out of the box, with the same field paths
as a ROS bag, since the messages are shaped like ``sensor_msgs/JointState``),
``mcap cat --json`` prints them, every channel uses one code path, and the SDK
needs no extra dependency.  The price: ``ros2 bag play`` cannot republish JSON
channels; a ROS user who needs that can convert ``/joint_states`` to CDR with
``mcap-ros2-support`` offline.  The command channel has no ROS message type
anyway (``mode[]``, gains).

Timing
------
Log time (and ``header.stamp``) is robot clock time in nanoseconds: simulated
time in lockstep, time since connect in real time.  A ``/joint_states``
message stamped ``t`` is the state measured at the end of the tick that
started at ``t - period``; the ``/joint_commands`` message applied during that
tick is stamped ``t - period`` (when it was written).

``/joint_commands`` is change-based: a message is written at every tick whose
setpoint differs from the previous tick's, at the tick just before each change
(so a line plot shows holds as flat segments) and at the first and last tick
of every buffer block; sample-and-hold reconstructs the setpoint of every tick
exactly.  ``record_rate`` decimates ``/joint_states`` only: commands are never
decimated, so a decimated recording still replays exactly.

Cost on the control loop
------------------------
The recorder's tick hook copies a few numpy rows into preallocated blocks of
``BLOCK_TICKS`` ticks (about 3 µs per tick for a 3-joint arm); no logging and
no encoding per tick.  When a block is full the rows to keep are selected
(vectorized, well under a millisecond) and queued; :meth:`Recorder.finish`
encodes and writes them after the run.  Only a long run whose queue exceeds
``DRAIN_AFTER_TICKS`` ticks (about 2 minutes at 500 Hz) has the tick hook
write a few queued messages per tick, which bounds memory at a steady cost of
tens of microseconds per tick.  Writing whole blocks at once in the loop (or
in a thread: the GIL hand-offs stalled the loop for up to a second under load)
would pause the control loop long enough to trip the safety layer's stall
watchdog.  Call :meth:`Recorder.finish` after the robot is closed, as the CLI
does, so that the final write cannot stall a running control loop.

State-machine transitions
-------------------------
The recorder registers a transition listener
(:meth:`StateMachine.add_transition_listener <agentsdk.statemachine.StateMachine.add_transition_listener>`)
while it is attached, and keeps the records of machines whose ``robot`` is the
recorded robot.

Replay
------
:func:`replay` connects a fresh robot (lockstep for simulators), and an
updater writes the recorded setpoint (position, velocity, effort, kp, kd,
enabled, mode) into the robot's setpoint (a COMMAND-phase tick hook) at the same tick it was
applied in the recording.  The safety layer filters it again, which leaves it
unchanged (the recorded setpoint is already limited and ramped); the command
watchdog is turned off because no commands are sent.  Lockstep MuJoCo is
deterministic, so a MuJoCo recording replays into MuJoCo bit for bit.
"""

from . import _recorder
from ._channels import FORMAT, TOPICS, robot_spec_for_metadata
from ._channels import JOINT_COMMAND_SCHEMA as JOINT_COMMAND_SCHEMA
from ._channels import JOINT_COMMANDS as JOINT_COMMANDS
from ._channels import JOINT_STATE_SCHEMA as JOINT_STATE_SCHEMA
from ._channels import JOINT_STATES as JOINT_STATES
from ._channels import METADATA_NAME as METADATA_NAME
from ._channels import ROBOT_DESCRIPTION as ROBOT_DESCRIPTION
from ._channels import SAFETY_EVENT_SCHEMA as SAFETY_EVENT_SCHEMA
from ._channels import SAFETY_EVENTS as SAFETY_EVENTS
from ._channels import TF as TF
from ._channels import TRANSITION_SCHEMA as TRANSITION_SCHEMA
from ._channels import TRANSITIONS as TRANSITIONS
from ._reader import RunData, read_recording
from ._recorder import BLOCK_TICKS, Recorder
from ._recorder import DRAIN_AFTER_TICKS as DRAIN_AFTER_TICKS
from ._recorder import FLUSH_INTERVAL as FLUSH_INTERVAL
from ._recorder import RECORDER_ORDER as RECORDER_ORDER
from ._replay import ReplayResult, replay

# re-bound here with their documentation, which Sphinx reads from the assignments in this module
#: default rate of /tf (Hz of robot time): smooth in Foxglove, cheap for a 30-link robot
TF_RATE = _recorder.TF_RATE
#: ``--record-format`` choices
RECORD_FORMATS = _recorder.RECORD_FORMATS

__all__ = [
    "BLOCK_TICKS",
    "FORMAT",
    "RECORD_FORMATS",
    "TF_RATE",
    "TOPICS",
    "Recorder",
    "ReplayResult",
    "RunData",
    "read_recording",
    "replay",
    "robot_spec_for_metadata",
]

for _name in __all__:
    _obj = globals()[_name]
    if getattr(_obj, "__module__", "").startswith(__name__ + "."):
        _obj.__module__ = __name__  # documented and pickled as agentsdk.recording.X
