"""Episode records from ROS 2 logs (rosbag2 folders), read with the pure-Python ``rosbags``: no ROS install needed.

One bag becomes one :class:`~efficienttrack.data.records.EpisodeRecord` on the 20 Hz control grid. Two topics are read,
and a third when given:

- the joint states, ``sensor_msgs/msg/JointState`` (``/joint_states`` by default): ``position`` → ``q`` (rad) and
  ``velocity`` → ``qd`` (rad/s), picked out of ``name`` by a joint map (package joint → ROS joint name; by default
  a joint named ``boom`` or ``boom_joint`` is the boom, and so on); other joints in the message are ignored;
- the reference sent to the machine's position controller → ``q_ref``, either ``std_msgs/msg/Float64MultiArray``
  (``data``: the 4 positions in the order boom, arm, bucket, swing, as ros2_control's position controllers take
  them; stamped with the bag's receive time, the message has no header), ``sensor_msgs/msg/JointState``
  (``position`` by name, through the same joint map) or ``trajectory_msgs/msg/JointTrajectory`` (the command of
  ros2_control's joint_trajectory_controller: ``points[0].positions`` by ``joint_names``, through the same joint map);
- optionally the desired positions q* → ``q_des`` (same three types); without it the reference is the desired
  position (``q_des = q_ref``: a log of the controller alone, as the PD logs are).

A JointTrajectory becomes one reference sample: its first point, the first target the controller moves towards (the
controller requires the points' ``time_from_start`` to increase, so it is also the earliest), stamped at the
message's ``header.stamp``, the trajectory's start, or at its receive time where that stamp is zero ("start now",
as the controller reads it) or with ``clock="bag"``. ``time_from_start`` is not added to the stamp, and later points
are ignored: a streamed command holds one point; of a multi-point trajectory only the first target is recorded (the
record's ``meta["joint_trajectory"]`` says so and counts such messages per topic). A message without points, with a
first point whose ``positions`` do not match ``joint_names``, or without a mapped joint is refused.

Resampling: the grid is ``t_k = t_0 + k·dt`` over the time all topics cover. The joint states are interpolated
linearly at ``t_k`` (the swing through its wrap at ±π). A reference is a command the controller holds until the
next one: ``q_ref[k]`` is the last reference published before ``t_{k+1}``, the one the machine moved towards
between steps k and k+1 (the records' time alignment, :mod:`efficienttrack.data.records`); ``q_des`` likewise. The
swing is wrapped to (−π, π]. ``u`` is None (a ROS log holds no valve commands). The grid, the interpolation and the hold
are :mod:`efficienttrack.data.tabular`'s, shared with the import of CSV and Parquet tables.

Stamps: ``header.stamp`` of the joint states with ``clock="header"`` (the default; the time the sensor was read), or
the bag's receive time of every message with ``clock="bag"`` (for drivers that leave the stamp at zero, or when the
topics' clocks differ). Bad logs are refused with the bag, topic and field named: a missing topic or one of another
type, joint names the map does not find, a JointTrajectory without points, too few messages, stamps that do not
increase, gaps longer than ``max_gap``, topics that do not overlap in time.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import ReaderError
from rosbags.typesys import Stores, get_typestore

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_file_name
from efficienttrack.core.joints import DT, JOINT_NAMES, MAX_ABS_ANGLE, N_JOINTS, SWING
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.tabular import MAX_GAP, check_max_gap, control_grid, hold, interpolate

JOINT_STATE = "sensor_msgs/msg/JointState"
"""The joint states' message type (and one of the reference's)."""
FLOAT_ARRAY = "std_msgs/msg/Float64MultiArray"
"""The other type a reference may have: 4 positions in joint order, no names, no header."""
JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
"""joint_trajectory_controller's command type: the first point's positions by joint name are the reference."""
REFERENCE_TYPES = (FLOAT_ARRAY, JOINT_STATE, JOINT_TRAJECTORY)
"""Message types a reference or desired-position topic may have."""
FIELDS = {FLOAT_ARRAY: "data", JOINT_STATE: "position", JOINT_TRAJECTORY: "points[0].positions"}
"""The field the positions come from, per message type."""
TRAJECTORY_RULE = (
    "points[0] of each JointTrajectory is the reference, stamped at header.stamp (receive time where zero or with "
    "--clock bag); time_from_start is not added and later points are ignored"
)
"""How a JointTrajectory becomes a reference sample, as the record's meta says it."""
JOINT_STATES_TOPIC = "/joint_states"
"""The joint states' topic by default (the ROS convention)."""
CLOCKS = ("header", "bag")
"""Where the joint states' stamps come from: their ``header.stamp``, or the bag's receive time."""


def joint_map(pairs: Sequence[str] | Mapping[str, str] | None) -> dict[str, tuple[str, ...]]:
    """The ROS joint names to look for, per package joint: the defaults amended by the user's ``joint=ros_name`` pairs.

    Args:
        pairs: ``["boom=boom_joint", ...]`` (``--joint`` on the command line) or ``{"boom": "boom_joint"}``; a joint not
            given is looked for under its defaults, ``boom`` or ``boom_joint`` and so on (less any name given for
            another joint); None for the defaults alone.

    Returns:
        ``{joint: (ROS names accepted, the first one found wins)}`` for boom, arm, bucket, swing.

    Raises:
        EfficientTrackError: a pair without ``=``, an unknown package joint, an empty name, or one ROS name for two joints.
    """
    given: dict[str, str] = {}
    for joint, ros_name in pairs.items() if isinstance(pairs, Mapping) else (p.partition("=")[::2] for p in pairs or ()):
        if joint not in JOINT_NAMES or not ros_name:
            raise EfficientTrackError(
                f"--joint '{joint}={ros_name}': expected JOINT=ROS_NAME with JOINT one of {', '.join(JOINT_NAMES)}"
            )
        given[joint] = ros_name
    twice = sorted({name for name in given.values() if list(given.values()).count(name) > 1})
    if twice:
        raise EfficientTrackError(f"--joint: the ROS joint '{twice[0]}' is given for two joints")
    taken = set(given.values())
    return {
        joint: (given[joint],) if joint in given else tuple(n for n in (joint, f"{joint}_joint") if n not in taken)
        for joint in JOINT_NAMES
    }


class _Topic:
    """One topic's messages: (M,) stamps s, (M, 4) positions rad in joint order, (M, 4) velocities rad/s or None.

    ``kind`` is the message type; ``stamped_by`` names where the stamps come from (``header.stamp``, ``receive time``,
    or for a JointTrajectory both, per message), and ``field`` the field the positions come from, for messages;
    ``multi_point`` counts the JointTrajectory messages with more than one point (0 for the other types).
    """

    def __init__(
        self,
        stamps: list[float],
        positions: list[np.ndarray],
        velocities: list[np.ndarray] | None,
        kind: str,
        stamped_by: str,
        multi_point: int = 0,
    ) -> None:
        self.kind, self.stamped_by, self.multi_point = kind, stamped_by, multi_point
        self.field = FIELDS[kind]
        self.stamps = np.asarray(stamps, dtype=np.float64)
        self.positions = np.asarray(positions, dtype=np.float64).reshape(-1, N_JOINTS)
        self.velocities = None if velocities is None else np.asarray(velocities, dtype=np.float64).reshape(-1, N_JOINTS)


def read_rosbag(
    bag: str | Path,
    reference: str,
    desired: str | None = None,
    joint_states: str = JOINT_STATES_TOPIC,
    joints: Sequence[str] | Mapping[str, str] | None = None,
    clock: str = "header",
    max_gap: float = MAX_GAP,
) -> EpisodeRecord:
    """Read one rosbag2 folder into an episode on the 20 Hz grid (module docstring: topics, resampling, stamps).

    Args:
        bag: the rosbag2 folder (``metadata.yaml`` and its ``.db3``/``.mcap`` files).
        reference: the topic of the references sent to the position controller → ``q_ref``.
        desired: the topic of the desired positions → ``q_des``, or None (``q_des = q_ref``).
        joint_states: the ``sensor_msgs/msg/JointState`` topic → ``q``, ``qd``.
        joints: the joint map, ``joint=ros_name`` pairs or a mapping (:func:`joint_map`); None for the defaults.
        clock: ``"header"`` (the joint states' ``header.stamp``) or ``"bag"`` (receive times) for every message of a
            JointState or JointTrajectory topic (a JointTrajectory whose ``header.stamp`` is zero takes its receive
            time with either); a Float64MultiArray topic is always stamped with its receive time.
        max_gap: the longest gap between two messages of a topic, s.

    Returns:
        The validated record: q, qd, q_ref, q_des (T, 4), u None, t (T,) s from the grid's start; ``meta`` names the
        bag, its topics and the grid's start stamp, and, when a topic is a JointTrajectory, the point rule and the
        count of multi-point messages per topic (``joint_trajectory``). Its name is the bag folder's.

    Raises:
        EfficientTrackError: naming the bag, and the topic and field where one is at fault.
    """
    bag = Path(bag)
    if clock not in CLOCKS:
        raise EfficientTrackError(f"--clock '{clock}': expected one of {', '.join(CLOCKS)}")
    check_max_gap(max_gap)
    if not bag.is_dir():
        problem = "no such folder" if not bag.exists() else "not a folder"
        raise EfficientTrackError(
            f"{bag}: {problem}; a rosbag2 log is a folder holding metadata.yaml (ROS 1 .bag files are not read)"
        )
    name = check_file_name(bag.resolve().name, f"{bag}: the bag folder's name")
    names = joint_map(joints)
    wanted = {"joint_states": joint_states, "reference": reference, **({"desired": desired} if desired else {})}
    try:
        with AnyReader([bag], default_typestore=get_typestore(Stores.LATEST)) as reader:
            topics = {role: _read_topic(reader, bag, topic, role, names, clock) for role, topic in wanted.items()}
    except (AnyReaderError, ReaderError, OSError, UnicodeDecodeError) as exc:
        raise EfficientTrackError(f"{bag}: not a readable rosbag2 log ({exc})") from exc
    for role, topic in wanted.items():
        _check_stamps(topics[role], bag, topic, max_gap)
        _check_angles(topics[role], bag, topic)

    start = max(float(topic.stamps[0]) for topic in topics.values())
    end = min(float(topic.stamps[-1]) for topic in topics.values())
    grid = control_grid(start, end, str(bag))
    if len(grid) < 2:
        spans = ", ".join(f"{wanted[r]} {t.stamps[0]:.3f}…{t.stamps[-1]:.3f} s" for r, t in topics.items())
        raise EfficientTrackError(
            f"{bag}: the topics overlap for fewer than 2 control steps of {DT} s ({spans})"
            + (
                "; if their clocks differ (sim time?), read every stamp from the bag with --clock bag"
                if clock == "header"
                else ""
            )
        )
    states = topics["joint_states"]
    assert states.velocities is not None  # _read_topic keeps the velocities of the joint states' topic
    q = interpolate(states.stamps, states.positions, grid, unwrap_swing=True)
    qd = interpolate(states.stamps, states.velocities, grid, unwrap_swing=False)
    # a reference is held from its publication on: the last one strictly before t_k + dt is the one of step k → k+1
    q_ref = hold(topics["reference"].stamps, topics["reference"].positions, grid + DT, strict=True)
    q_des = hold(topics["desired"].stamps, topics["desired"].positions, grid + DT, strict=True) if desired else q_ref.copy()
    for angles in (q, q_ref, q_des):
        angles[:, SWING] = wrap(angles[:, SWING])
    meta: dict[str, Any] = {
        "name": name,
        "source": "rosbag2",
        "bag": str(bag),
        "topics": wanted,
        "clock": clock,
        "start_stamp": start,
        "joints": {joint: list(ros_names) for joint, ros_names in names.items()},
    }
    trajectories = {wanted[role]: t.multi_point for role, t in topics.items() if t.kind == JOINT_TRAJECTORY}
    if trajectories:
        meta["joint_trajectory"] = {"rule": TRAJECTORY_RULE, "multi_point_messages": trajectories}
    record = EpisodeRecord(q=q, qd=qd, q_ref=q_ref, q_des=q_des, u=None, t=grid - start, meta=meta)
    return record.validate(f"{bag} (rosbag2)")


def _read_topic(reader: AnyReader, bag: Path, topic: str, role: str, names: dict[str, tuple[str, ...]], clock: str) -> _Topic:
    """Every message of ``topic`` as stamps and (M, 4) arrays in joint order; velocities for the joint states only."""
    connections = [c for c in reader.connections if c.topic == topic]
    types = sorted({c.msgtype for c in connections})
    accepted = (JOINT_STATE,) if role == "joint_states" else REFERENCE_TYPES
    if not connections:
        present = ", ".join(f"{c.topic} ({c.msgtype})" for c in reader.connections) or "none"
        raise EfficientTrackError(f"{bag}: no topic {topic} (--{role.replace('_', '-')}); topics in the bag: {present}")
    if len(types) != 1 or types[0] not in accepted:
        raise EfficientTrackError(f"{bag}: topic {topic} has type {', '.join(types)}; expected {' or '.join(accepted)}")
    kind = types[0]
    stamps: list[float] = []
    positions: list[np.ndarray] = []
    velocities: list[np.ndarray] | None = [] if role == "joint_states" else None
    columns: dict[tuple[str, ...], list[int]] = {}  # the joints' indices, per list of names seen
    header_stamps = multi_point = 0  # JointTrajectory: messages stamped by their header, with more than one point
    for index, (connection, received, raw) in enumerate(reader.messages(connections=connections)):
        msg: Any = reader.deserialize(raw, connection.msgtype)  # a message class the bag's type store builds
        where = f"{bag}: topic {topic}, message {index}"
        if kind == FLOAT_ARRAY:
            data = np.asarray(msg.data, dtype=np.float64)
            if data.shape != (N_JOINTS,):
                raise EfficientTrackError(
                    f"{where}: field 'data' holds {data.size} values; expected {N_JOINTS} (boom, arm, bucket, swing, rad)"
                )
            stamps.append(received * 1e-9)
            positions.append(data)
            continue
        if kind == JOINT_TRAJECTORY:
            key = tuple(msg.joint_names)
            if not msg.points:
                raise EfficientTrackError(
                    f"{where}: field 'points' is empty; a JointTrajectory reference needs a point (its first is the reference)"
                )
            if key not in columns:
                columns[key] = _columns(key, names, where, "joint_names")
            position = np.asarray(msg.points[0].positions, dtype=np.float64)
            if position.shape != (len(key),):
                raise EfficientTrackError(
                    f"{where}: field 'points[0].positions' holds {position.size} values for {len(key)} joint names"
                )
            positions.append(position[columns[key]])
            multi_point += len(msg.points) > 1
            stamp = msg.header.stamp
            if clock == "header" and (
                stamp.sec or stamp.nanosec
            ):  # in ns first, as a receive time: the same instant, the same s
                stamps.append((stamp.sec * 1_000_000_000 + stamp.nanosec) * 1e-9)
                header_stamps += 1
            else:  # a zero stamp means "start now": the controller takes the time it received the message
                stamps.append(received * 1e-9)
            continue
        key = tuple(msg.name)
        if key not in columns:
            columns[key] = _columns(key, names, where)
        cols = columns[key]
        position = np.asarray(msg.position, dtype=np.float64)
        if position.shape != (len(key),):
            raise EfficientTrackError(f"{where}: field 'position' holds {position.size} values for {len(key)} names")
        positions.append(position[cols])
        if velocities is not None:
            velocity = np.asarray(msg.velocity, dtype=np.float64)
            if velocity.shape != (len(key),):
                raise EfficientTrackError(
                    f"{where}: field 'velocity' holds {velocity.size} values for {len(key)} names; the records need the "
                    "measured joint velocities (rad/s)"
                )
            velocities.append(velocity[cols])
        stamp = msg.header.stamp
        stamps.append(stamp.sec + stamp.nanosec * 1e-9 if clock == "header" else received * 1e-9)
    if len(stamps) < 2:
        raise EfficientTrackError(f"{bag}: topic {topic} has {len(stamps)} message(s); at least 2 are needed")
    stamped_by = "header.stamp" if kind == JOINT_STATE and clock == "header" else "receive time"
    if kind == JOINT_TRAJECTORY and header_stamps:
        stamped_by = "header.stamp" if header_stamps == len(stamps) else "header.stamp (receive time where zero)"
    return _Topic(stamps, positions, velocities, kind, stamped_by, multi_point)


def _columns(key: tuple[str, ...], names: dict[str, tuple[str, ...]], where: str, field: str = "name") -> list[int]:
    """Indices of boom, arm, bucket, swing in a JointState's ``name`` (or a JointTrajectory's ``joint_names``) list."""
    cols = []
    for joint, ros_names in names.items():
        found = [key.index(n) for n in ros_names if n in key]
        if not found:
            raise EfficientTrackError(
                f"{where}: field '{field}' has no joint {' or '.join(ros_names) or 'left'} for the {joint} (names: "
                f"{', '.join(key) or 'none'}); map it with --joint {joint}=ROS_NAME"
            )
        cols.append(found[0])
    return cols


def _check_stamps(topic: _Topic, bag: Path, name: str, max_gap: float) -> None:
    """A topic's stamps must increase, without gaps longer than ``max_gap`` s."""
    stamps, steps = topic.stamps, np.diff(topic.stamps)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        hint = "; with stamps left at zero or reset, read the receive times with --clock bag"
        raise EfficientTrackError(
            f"{bag}: topic {name}: field {topic.stamped_by} does not increase at message {k} ({stamps[k - 1]:.9f} s, then "
            f"{stamps[k]:.9f} s)" + (hint if topic.stamped_by.startswith("header.stamp") else "")
        )
    if np.any(steps > max_gap):
        k = int(np.argmax(steps > max_gap)) + 1
        raise EfficientTrackError(
            f"{bag}: topic {name}: field {topic.stamped_by} jumps by {steps[k - 1]:.3f} s before message {k} "
            f"({stamps[k - 1] - stamps[0]:.3f} s into the topic), a gap longer than --max-gap {max_gap} s; split the log "
            "there or allow a longer gap"
        )


def _check_angles(topic: _Topic, bag: Path, name: str) -> None:
    """Positions beyond ±2π rad are refused before the swing is wrapped (wrapping would hide degrees)."""
    peak = np.abs(topic.positions).max(axis=0)
    if np.any(peak > MAX_ABS_ANGLE):
        joint = int(np.argmax(peak > MAX_ABS_ANGLE))
        raise EfficientTrackError(
            f"{bag}: topic {name}: field '{topic.field}' reaches {peak[joint]:.3g} at the {JOINT_NAMES[joint]}, beyond "
            "±2π rad: degrees? (the records hold radians; a swing past a full turn must be wrapped to ±π)"
        )
