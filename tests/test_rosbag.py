"""rosbag2 logs → episode records (efficienttrack.data.rosbag): bags written here with the rosbags writer, no ROS needed."""

import time

import numpy as np
import pytest
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import output_lock
from efficienttrack.core.joints import DT
from efficienttrack.data.records import load_records, save_records
from efficienttrack.data.rosbag import joint_map, read_rosbag

TYPES = get_typestore(Stores.ROS2_HUMBLE)
JointState = TYPES.types["sensor_msgs/msg/JointState"]
Float64MultiArray = TYPES.types["std_msgs/msg/Float64MultiArray"]
String = TYPES.types["std_msgs/msg/String"]
Header = TYPES.types["std_msgs/msg/Header"]
Time = TYPES.types["builtin_interfaces/msg/Time"]
Layout = TYPES.types["std_msgs/msg/MultiArrayLayout"]
JointTrajectory = TYPES.types["trajectory_msgs/msg/JointTrajectory"]
JointTrajectoryPoint = TYPES.types["trajectory_msgs/msg/JointTrajectoryPoint"]
Duration = TYPES.types["builtin_interfaces/msg/Duration"]

T0 = 100.0
"""The log's first stamp, s."""
NAMES = ["extra_joint", "swing_joint", "bucket_joint", "boom_joint", "arm_joint"]
"""A driver's order, with a joint the records do not use."""
JOINTS = ("boom_joint", "arm_joint", "bucket_joint", "swing_joint")
"""The package's joints under their default ROS names."""
OFFSET = np.array([0.1, -0.5, 0.3, 3.0])
SLOPE = np.array([0.2, -0.1, 0.05, 0.5])
"""q(t) = OFFSET + SLOPE·(t − T0) rad per joint (boom, arm, bucket, swing): linear, so interpolation is exact; the swing
passes +π at t − T0 ≈ 0.28 s and is published wrapped, as a continuous joint's driver does."""


def joint_state(stamp, q, qd, names=NAMES, joints=JOINTS):
    """A JointState with boom, arm, bucket, swing (named ``joints``) placed in ``names`` (any other joint at 9.0)."""
    pick = [joints.index(n) if n in joints else None for n in names]
    position = np.array([9.0 if i is None else q[i] for i in pick])
    velocity = np.array([0.0 if i is None else qd[i] for i in pick]) if qd is not None else np.array([], dtype=float)
    sec = int(np.floor(stamp))
    return JointState(Header(Time(sec, round((stamp - sec) * 1e9)), ""), list(names), position, velocity, np.array([]))


def array(values):
    return Float64MultiArray(Layout([], 0), np.asarray(values, dtype=np.float64))


def trajectory(stamp, points, names=NAMES, joints=JOINTS):
    """A JointTrajectory stamped ``stamp`` s (0: "start now") with one point per (4,) ``points`` row (boom, arm, bucket,
    swing rad, the joints named ``joints``) placed in ``names`` (any other joint at 9.0), 0.05 s apart from 0.05 s."""
    pick = [joints.index(n) if n in joints else None for n in names]
    sec = int(np.floor(stamp))
    return JointTrajectory(
        Header(Time(sec, round((stamp - sec) * 1e9)), ""),
        list(names),
        [
            JointTrajectoryPoint(
                np.array([9.0 if i is None else q[i] for i in pick]),
                np.zeros(len(names)),
                np.array([]),
                np.array([]),
                Duration(0, (j + 1) * 50_000_000),
            )
            for j, q in enumerate(points)
        ],
    )


def trajectories(header_delay=None, later_points=0, **names):
    """references() as JointTrajectory messages: one point each, plus ``later_points`` points at 7.0 rad (ignored, or
    they would be refused as beyond ±2π).

    ``header_delay`` None leaves ``header.stamp`` at zero; else the header is stamped with the array's receive time and
    the message received ``header_delay`` s later."""
    messages = []
    for received, msg in references():
        points = [msg.data, *[np.full(4, 7.0)] * later_points]
        stamp = 0.0 if header_delay is None else received
        messages.append((received + (header_delay or 0.0), trajectory(stamp, points, **names)))
    return messages


def write_bag(path, topics):
    """``topics``: {topic: [(receive time s, message), ...]}; the folder is a rosbag2 log (sqlite3)."""
    with Writer(path, version=9) as writer:
        for topic, messages in topics.items():
            connection = writer.add_connection(topic, messages[0][1].__msgtype__, typestore=TYPES)
            for received, msg in messages:
                writer.write(connection, round(received * 1e9), TYPES.serialize_cdr(msg, msg.__msgtype__))
    return path


def states(seconds=2.0, rate=100.0, velocity=True, zero_stamps=False, **names):
    """Joint states at ``rate`` Hz from T0, received 2 ms after their stamp (``names``: joint_state's names/joints)."""
    stamps = T0 + np.arange(round(seconds * rate)) / rate
    q = OFFSET + SLOPE * (stamps - T0)[:, None]
    q[:, 3] = wrap(q[:, 3])
    qd = SLOPE if velocity else None
    return [(s + 0.002, joint_state(0.0 if zero_stamps else s, qs, qd, **names)) for s, qs in zip(stamps, q, strict=True)]


def references(seconds=2.0, start=T0):
    """A reference per control step k, published 10 ms after the step's reading: value k·0.01 + joint index."""
    steps = np.arange(round((seconds - (start - T0)) / DT))
    return [(start + k * DT + 0.01, array(k * 0.01 + np.arange(4) * 0.1)) for k in steps]


@pytest.fixture
def bag(tmp_path):
    return write_bag(tmp_path / "cycle_01", {"/joint_states": states(), "/cmd": references()})


def test_a_bag_reads_back_on_the_control_grid(bag, tmp_path):
    record = read_rosbag(bag, "/cmd")
    T = len(record)
    # overlap: joint states from T0 (last 101.99), references received from T0 + 0.01 (last 101.96)
    assert T == 40 and record.u is None and record.meta["name"] == "cycle_01"
    np.testing.assert_allclose(record.t, DT * np.arange(T), atol=1e-9)
    grid = 0.01 + DT * np.arange(T)
    expected = OFFSET + SLOPE * grid[:, None]
    expected[:, 3] = wrap(expected[:, 3])
    np.testing.assert_allclose(record.q, expected, atol=1e-6)  # the swing interpolated through its wrap at +π
    assert record.q[:, 3].min() < -3 and record.q[:, 3].max() > 3
    np.testing.assert_allclose(record.qd, np.broadcast_to(SLOPE, (T, 4)), atol=1e-12)
    # q_ref[k]: the reference published in step k (at t_k + 0.01 − 0.01 = grid time), held until step k + 1
    np.testing.assert_allclose(record.q_ref, np.arange(T)[:, None] * 0.01 + np.arange(4) * 0.1, atol=1e-12)
    np.testing.assert_array_equal(record.q_des, record.q_ref)


def test_desired_topic_joint_map_and_receive_times(tmp_path):
    names = {"names": ["j_swing", "j_boom", "j_arm", "j_bucket"], "joints": ("j_boom", "j_arm", "j_bucket", "j_swing")}
    desired = [(T0 + k * DT + 0.005, joint_state(T0 + k * DT, np.full(4, 0.5 + k * 0.001), None, **names)) for k in range(40)]
    zero_stamped = states(zero_stamps=True, **names)
    path = write_bag(tmp_path / "b", {"/joint_states": zero_stamped, "/cmd": references(), "/desired": desired})
    joints = ["boom=j_boom", "arm=j_arm", "bucket=j_bucket", "swing=j_swing"]
    with pytest.raises(EfficientTrackError, match="field header.stamp does not increase at message 1.*--clock bag"):
        read_rosbag(path, "/cmd", "/desired", joints=joints)
    record = read_rosbag(path, "/cmd", "/desired", joints=joints, clock="bag")
    assert len(record) == 39  # the joint states are received from T0 + 0.002 to 101.992 s, the references from T0 + 0.01
    # the grid starts at the first reference received (T0 + 0.01); step k holds the desired received at T0 + k·dt + 0.055
    np.testing.assert_allclose(record.q_des, 0.5 + (np.arange(39)[:, None] + 1) * 0.001 + np.zeros(4), atol=1e-12)
    assert record.meta["topics"] == {"joint_states": "/joint_states", "reference": "/cmd", "desired": "/desired"}


def test_import_rosbag_command(bag, tmp_path):
    out = tmp_path / "records"
    result = CliRunner().invoke(app, ["import-rosbag", str(bag), "--reference", "/cmd", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "wrote 1 episode(s), 40 steps" in result.output
    (loaded,) = load_records(out)
    np.testing.assert_array_equal(loaded.q_ref, read_rosbag(bag, "/cmd").q_ref)
    again = CliRunner().invoke(app, ["import-rosbag", str(bag), "--reference", "/nope", "--out", str(tmp_path / "o")])
    assert isinstance(again.exception, EfficientTrackError) and "no topic /nope" in str(again.exception)
    assert not (tmp_path / "o").exists()  # nothing is written before every bag is read


def test_import_rosbag_and_convert_refuse_a_folder_being_written(bag, tmp_path):
    out = tmp_path / "records"
    runner = CliRunner()
    with output_lock(out):
        imported = runner.invoke(app, ["import-rosbag", str(bag), "--reference", "/cmd", "--out", str(out), "--force"])
        save_records([read_rosbag(bag, "/cmd")], tmp_path / "npz")
        converted = runner.invoke(app, ["convert", str(tmp_path / "npz"), "--out", str(out), "--force"])
        for result in (imported, converted):
            assert isinstance(result.exception, EfficientTrackError) and "another efficienttrack process" in str(
                result.exception
            )
        assert list(out.iterdir()) == []


def test_joint_map_defaults_and_user_names():
    assert joint_map(None)["boom"] == ("boom", "boom_joint")
    names = joint_map(["arm=boom", "swing=slew"])
    assert names["arm"] == ("boom",) and names["boom"] == ("boom_joint",) and names["swing"] == ("slew",)
    for bad, message in (
        (["elbow=j1"], "JOINT one of boom"),
        (["boom"], "expected JOINT=ROS_NAME"),
        (["boom=a", "arm=a"], "two"),
    ):
        with pytest.raises(EfficientTrackError, match=message):
            joint_map(bad)


def deg_swing(msg):
    """The message with its swing in degrees."""
    position = np.array(msg.position)
    position[NAMES.index("swing_joint")] = np.rad2deg(position[NAMES.index("swing_joint")])
    return JointState(msg.header, msg.name, position, msg.velocity, msg.effort)


def bad_bags(tmp_path):
    """(bag, read_rosbag options, message): each a log a user may really have."""
    gap = [m for m in states() if not 100.5 <= m[0] < 101.2]
    back = states()
    back[7], back[8] = (back[7][0], back[8][1]), (back[8][0], back[7][1])  # received in order, stamped out of order
    cases = {
        "wrong_type": ({"/joint_states": states(), "/cmd": [(T0 + k, String("x")) for k in range(3)]}, {}),
        "one_reference": ({"/joint_states": states(), "/cmd": references()[:1]}, {}),
        "gap": ({"/joint_states": gap, "/cmd": references()}, {}),
        "back": ({"/joint_states": back, "/cmd": references()}, {}),
        "no_velocity": ({"/joint_states": states(velocity=False), "/cmd": references()}, {}),
        "three_values": ({"/joint_states": states(), "/cmd": [(T0 + k * DT, array([0, 0, 0])) for k in range(40)]}, {}),
        "no_overlap": ({"/joint_states": states(1.0), "/cmd": references(3.0, start=T0 + 1.5)}, {}),
        "swing_degrees": ({"/joint_states": [(r, deg_swing(m)) for r, m in states()], "/cmd": references()}, {}),
        "unknown_joint": ({"/joint_states": states(), "/cmd": references()}, {"joints": ["boom=hydraulic_boom"]}),
        "missing_topic": ({"/joint_states": states(), "/cmd": references()}, {"reference": "/commands"}),
        "degrees": ({"/joint_states": states(), "/cmd": [(r, array(np.rad2deg(m.data) + 30)) for r, m in references()]}, {}),
    }
    return {name: (write_bag(tmp_path / name, topics), options) for name, (topics, options) in cases.items()}


EXPECTED = {
    "wrong_type": "topic /cmd has type std_msgs/msg/String; expected std_msgs/msg/Float64MultiArray or",
    "one_reference": "topic /cmd has 1 message\\(s\\); at least 2",
    "gap": "topic /joint_states: field header.stamp jumps by 0.710 s before message 50 .* --max-gap 0.25",
    "back": "topic /joint_states: field header.stamp does not increase at message 8",
    "no_velocity": "topic /joint_states, message 0: field 'velocity' holds 0 values for 5 names",
    "three_values": "topic /cmd, message 0: field 'data' holds 3 values; expected 4",
    "no_overlap": "the topics overlap for fewer than 2 control steps",
    "unknown_joint": "topic /joint_states, message 0: field 'name' has no joint hydraulic_boom for the boom .*--joint boom=",
    "missing_topic": "no topic /commands \\(--reference\\); topics in the bag: /joint_states \\(sensor_msgs/msg/JointState\\)",
    "degrees": "topic /cmd: field 'data' reaches 52.3 at the boom, beyond ±2π rad: degrees\\?",
    "swing_degrees": "topic /joint_states: field 'position' reaches 180 at the swing, beyond ±2π rad",
}


def test_bad_logs_are_refused_naming_the_bag_topic_and_field(tmp_path):
    for name, (path, options) in bad_bags(tmp_path).items():
        with pytest.raises(EfficientTrackError, match=EXPECTED[name]) as caught:
            read_rosbag(path, **{"reference": "/cmd", **options})
        assert str(path) in str(caught.value), name


def test_not_a_bag(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(EfficientTrackError, match="empty: not a readable rosbag2 log"):
        read_rosbag(tmp_path / "empty", "/cmd")
    with pytest.raises(EfficientTrackError, match="no such folder"):
        read_rosbag(tmp_path / "missing", "/cmd")
    (tmp_path / "log.bag").write_bytes(b"#ROSBAG V2.0\n")
    with pytest.raises(EfficientTrackError, match="not a folder; .*ROS 1 .bag files are not read"):
        read_rosbag(tmp_path / "log.bag", "/cmd")
    (tmp_path / "damaged").mkdir()
    (tmp_path / "damaged" / "metadata.yaml").write_text("rosbag2_bagfile_information: [")
    with pytest.raises(EfficientTrackError, match="damaged: not a readable rosbag2 log"):
        read_rosbag(tmp_path / "damaged", "/cmd")


def same_record(record, expected):
    for field in ("q", "qd", "q_ref", "q_des", "t"):
        np.testing.assert_array_equal(getattr(record, field), getattr(expected, field), err_msg=field)


def test_a_joint_trajectory_reference_reads_as_the_equivalent_float_array(bag, tmp_path):
    expected = read_rosbag(bag, "/cmd")
    # header.stamp zero ("start now"): stamped at the receive time, as the Float64MultiArray; one point, the reference
    zero = write_bag(tmp_path / "zero", {"/joint_states": states(), "/cmd": trajectories()})
    record = read_rosbag(zero, "/cmd")
    same_record(record, expected)
    assert record.meta["joint_trajectory"]["multi_point_messages"] == {"/cmd": 0}
    assert "joint_trajectory" not in expected.meta
    # stamped by header.stamp, received 20 ms later, with two later points: the first point at the header's stamp
    late = write_bag(tmp_path / "late", {"/joint_states": states(), "/cmd": trajectories(0.02, later_points=2)})
    record = read_rosbag(late, "/cmd")
    same_record(record, expected)
    assert record.meta["joint_trajectory"]["multi_point_messages"] == {"/cmd": 40}
    assert "later points are ignored" in record.meta["joint_trajectory"]["rule"]
    # --clock bag: the receive time, as the Float64MultiArray received as late
    shifted = [(received + 0.02, msg) for received, msg in references()]
    array_late = write_bag(tmp_path / "array_late", {"/joint_states": states(), "/cmd": shifted})
    same_record(read_rosbag(late, "/cmd", clock="bag"), read_rosbag(array_late, "/cmd", clock="bag"))
    # the desired topic takes the type too
    desired = write_bag(tmp_path / "desired", {"/joint_states": states(), "/cmd": references(), "/des": trajectories()})
    np.testing.assert_array_equal(read_rosbag(desired, "/cmd", "/des").q_des, expected.q_ref)


def test_import_rosbag_maps_joint_trajectory_names(bag, tmp_path):
    names = {
        "names": ["j_swing", "j_boom", "gripper", "j_arm", "j_bucket"],
        "joints": ("j_boom", "j_arm", "j_bucket", "j_swing"),
    }
    topics = {"/joint_states": states(**names), "/arm_controller/joint_trajectory": trajectories(**names)}
    path = write_bag(tmp_path / "jtc", topics)  # the joint states and the commands name the joints alike, in any order
    out = tmp_path / "records"
    joints = ["--joint", "boom=j_boom", "--joint", "arm=j_arm", "--joint", "bucket=j_bucket", "--joint", "swing=j_swing"]
    args = ["import-rosbag", str(path), "--reference", "/arm_controller/joint_trajectory", "--out", str(out), *joints]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    (loaded,) = load_records(out)
    same_record(loaded, read_rosbag(bag, "/cmd"))
    assert loaded.meta["joint_trajectory"]["multi_point_messages"] == {"/arm_controller/joint_trajectory": 0}


def test_bad_joint_trajectories_are_refused_in_one_line(tmp_path):
    def spoiled(msg, index=3):
        messages = trajectories()
        messages[index] = (messages[index][0], msg)
        return messages

    short = trajectory(0.0, [np.zeros(4)])
    short.points[0].positions = np.zeros(3)
    slew = {
        "names": ["slew", "boom_joint", "arm_joint", "bucket_joint"],
        "joints": ("boom_joint", "arm_joint", "bucket_joint", "slew"),
    }
    cases = {  # name: (reference messages, joint states' names, read_rosbag options, message)
        "empty_points": (
            spoiled(JointTrajectory(Header(Time(0, 0), ""), list(NAMES), [])),
            {},
            {},
            "topic /cmd, message 3: field 'points' is empty; a JointTrajectory reference needs a point",
        ),
        "unmapped": (
            trajectories(),
            slew,
            {"joints": ["swing=slew"]},
            "topic /cmd, message 0: field 'joint_names' has no joint slew for the swing \\(names: extra_joint, swing_joint, "
            ".*\\); map it with --joint swing=ROS_NAME",
        ),
        "partial": (
            spoiled(trajectory(0.0, [np.zeros(4)], names=NAMES[:4])),
            {},
            {},
            "topic /cmd, message 3: field 'joint_names' has no joint arm or arm_joint for the arm",
        ),
        "short_point": (
            spoiled(short, 5),
            {},
            {},
            "topic /cmd, message 5: field 'points\\[0\\].positions' holds 3 values for 5 joint names",
        ),
        "degrees": (
            [(r, trajectory(0.0, [np.rad2deg(m.data) + 30])) for r, m in references()],
            {},
            {},
            "topic /cmd: field 'points\\[0\\].positions' reaches 52.3 at the boom, beyond ±2π rad: degrees\\?",
        ),
    }
    for name, (messages, names, options, expected) in cases.items():
        path = write_bag(tmp_path / name, {"/joint_states": states(**names), "/cmd": messages})
        with pytest.raises(EfficientTrackError, match=expected) as caught:
            read_rosbag(path, "/cmd", **options)
        assert str(path) in str(caught.value) and "\n" not in str(caught.value), name


def test_a_log_longer_than_a_record_is_refused_before_it_is_built(tmp_path):
    far = T0 + 1e6  # two messages a topic, 10^6 s apart: 20 million control steps, some 3 GB of arrays
    q = OFFSET + np.zeros((1, 4))
    topics = {
        "/joint_states": [(T0 + 0.002, joint_state(T0, q[0], SLOPE)), (far + 0.002, joint_state(far, q[0], SLOPE))],
        "/cmd": [(T0 + 0.01, array(np.zeros(4))), (far + 0.01, array(np.zeros(4)))],
    }
    bag = write_bag(tmp_path / "long", topics)
    started = time.perf_counter()
    with pytest.raises(EfficientTrackError, match=r"long: the log spans 1000000 s, 20,000,000 control steps, more than"):
        read_rosbag(bag, "/cmd", max_gap=1e9)
    assert time.perf_counter() - started < 5
