r"""An example ROS 2 node around EfficientTrack's fixed-rate loop: joint states in, position references out.

Not part of the package and not imported by it: it needs rclpy, which comes with a ROS 2 installation, not from
PyPI (docs/ros2.md says how to get it). The tests only compile it.

The node is a :class:`efficienttrack.deploy.loop.Machine` adapter (:class:`RosMachine`) over rclpy: it subscribes to
``sensor_msgs/msg/JointState`` on ``joint_states`` and publishes each reference the loop sends as
``std_msgs/msg/Float64MultiArray`` (boom, arm, bucket, swing, rad) on ``~/reference``, the message ros2_control's
position controllers take (remap it to yours). It also publishes the desired position of every tick on
``~/desired``, so that a bag of the run imports with ``efficienttrack import-rosbag``. Everything else is the
package's: :func:`efficienttrack.deploy.deployment.deploy` runs :class:`~efficienttrack.deploy.loop.Loop` along
each reference, with its watchdogs, shadow mode, a = 0 at every start and end, and a JSONL log per reference.

Shadow mode first (the adjustment is computed and logged, the raw reference is sent)::

    python examples/ros2_node.py --refs refs/ --policy export/ --limits xe75_limits.yaml --out deploy/ros-shadow \
        --arm --shadow --ros-args -r /efficienttrack/reference:=/position_controller/commands

Nothing is published without ``--arm``; leave out ``--shadow`` only after reading the shadow logs.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import JOINT_NAMES
from efficienttrack.data.references import load_references
from efficienttrack.deploy.deployment import deploy
from efficienttrack.deploy.loop import LoopConfig
from efficienttrack.deploy.machine import MONOTONIC, Reading
from efficienttrack.systems.limits import GuardLimits

FIRST_READING_TIMEOUT = 2.0
"""Seconds to wait for the first joint state when the machine opens (the loop refuses to start without one)."""


class RosMachine:
    """The loop's machine adapter over an rclpy node: the newest JointState in, one Float64MultiArray per tick out.

    A reading is stamped with ``time.monotonic()`` when its message arrives (the loop's clock), so the loop's
    sensor age counts from reception. ``read`` returns the newest reading, the same one again when none came since
    (its age grows and the stale-sensor watchdog acts); a message without one of the joints is dropped.

    Args:
        node: the node (spun by an executor in another thread).
        joints: the ROS joint names of boom, arm, bucket, swing, in that order.
    """

    def __init__(self, node: Node, joints: list[str]) -> None:
        self.node, self.joints = node, joints
        self._lock = threading.Lock()
        self._latest: Reading | None = None
        self._subscription = self._publisher = None

    def __enter__(self) -> RosMachine:
        """Subscribe and advertise, then wait for the first joint state."""
        self._latest = None
        self._publisher = self.node.create_publisher(Float64MultiArray, "~/reference", 10)
        self._subscription = self.node.create_subscription(
            JointState, "joint_states", self._on_joint_state, qos_profile_sensor_data
        )
        deadline = time.monotonic() + FIRST_READING_TIMEOUT
        while self.read() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        return self

    def __exit__(self, *exc: object) -> None:
        """Stop listening and publishing."""
        self.node.destroy_subscription(self._subscription)
        self.node.destroy_publisher(self._publisher)
        self._subscription = self._publisher = None

    def _on_joint_state(self, msg: JointState) -> None:
        received = time.monotonic()
        try:
            index = [msg.name.index(name) for name in self.joints]
            obs = np.array([msg.position[i] for i in index] + [msg.velocity[i] for i in index], dtype=np.float64)
        except (ValueError, IndexError):  # a joint missing, or no velocities: not a usable sample
            self.node.get_logger().warning(f"joint_states without {self.joints} positions and velocities", once=True)
            return
        with self._lock:
            self._latest = Reading(obs, received)

    def read(self) -> Reading | None:
        """The newest joint state as (8,) [q rad, q̇ rad/s] stamped on the monotonic clock; None before the first."""
        with self._lock:
            return self._latest

    def send(self, q_ref: np.ndarray) -> np.ndarray:
        """Publish ``q_ref`` (4,) rad on ``~/reference``; returns it (the controller takes what is published)."""
        self._publisher.publish(Float64MultiArray(data=[float(x) for x in q_ref]))
        return np.asarray(q_ref, dtype=np.float64)


class PublishDesired:
    """A runtime that publishes each tick's desired position ``q*_{k+1}`` on ``~/desired``, then runs the real one.

    The loop calls ``step`` every tick with ``q*_{k+1} … q*_{k+F}``; the first is what the reference sent this tick
    adjusts. With it in the bag, ``import-rosbag --desired`` recovers ``q_des`` of an armed run.

    Args:
        runtime: the guarded runtime (``OnnxRuntime`` or the torch ``Runtime``).
        node: the node that publishes.
    """

    def __init__(self, runtime, node: Node) -> None:
        self.runtime, self.future_length = runtime, runtime.future_length
        self.publisher = node.create_publisher(Float64MultiArray, "~/desired", 10)

    def start(self, obs0: np.ndarray) -> None:
        """Start the runtime (``obs0`` (1, 8))."""
        self.runtime.start(obs0)

    def step(self, obs: np.ndarray, q_des_future: np.ndarray):
        """Publish ``q_des_future[0, 0]``, then step the runtime (``obs`` (1, 8), ``q_des_future`` (1, F, 4))."""
        self.publisher.publish(Float64MultiArray(data=[float(x) for x in q_des_future[0, 0]]))
        return self.runtime.step(obs, q_des_future)

    def sent_instead(self, q_ref: np.ndarray) -> None:
        """Tell the runtime what was really sent (``q_ref`` (1, 4))."""
        self.runtime.sent_instead(q_ref)

    def stop(self) -> None:
        """Stop the runtime."""
        self.runtime.stop()


def load_runtime(policy: Path, limits: GuardLimits):
    """An export folder in the torch-free ONNX runtime, or a ``policy.pt`` in the torch runtime."""
    if policy.is_dir():
        from efficienttrack.deploy.onnx_runtime import OnnxRuntime, load_onnx_policy

        return OnnxRuntime(load_onnx_policy(policy), limits=limits)
    from efficienttrack.deploy.runtime import Runtime
    from efficienttrack.learn.policy import load_policy

    return Runtime(load_policy(policy, "cpu"), limits=limits)


def main(argv: list[str]) -> int:
    """Parse the node's arguments (ROS arguments removed), run every reference, and return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--refs", type=Path, required=True, help="folder of references (rad, 20 Hz), run in turn")
    parser.add_argument("--policy", type=Path, required=True, help="export folder (policy.onnx + policy.json) or policy.pt")
    parser.add_argument("--limits", type=Path, required=True, help="the machine's limits file (GuardLimits)")
    parser.add_argument("--out", type=Path, required=True, help="new folder for the per-tick logs and deploy.json")
    parser.add_argument("--joints", nargs=4, default=[f"{j}_joint" for j in JOINT_NAMES], help="ROS names of the joints")
    parser.add_argument("--arm", action="store_true", help="allow motion (nothing is published without it)")
    parser.add_argument("--shadow", action="store_true", help="log the adjustment, send the raw reference (run this first)")
    args = parser.parse_args(argv)
    if not args.arm:
        print("ros2_node: add --arm to allow motion (with --shadow the raw reference is sent; start there)", file=sys.stderr)
        return 2
    if args.out.exists():
        print(f"ros2_node: {args.out} exists; give a new folder for this run's logs", file=sys.stderr)
        return 2

    limits = GuardLimits.load(args.limits)
    references = load_references(args.refs)
    node = Node("efficienttrack")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        runtime = PublishDesired(load_runtime(args.policy, limits), node)
        machine = RosMachine(node, args.joints)
        settings = {"policy": str(args.policy), "machine": "examples/ros2_node.py", "joints": args.joints}

        def report(result) -> None:
            node.get_logger().info(f"{result.name}: {result.reason}, {result.ticks} ticks")

        results = deploy(
            references, runtime, lambda ref: machine, limits, args.out, LoopConfig(), MONOTONIC, args.shadow, settings, report
        )
    except EfficientTrackError as exc:
        print(f"ros2_node: {exc}", file=sys.stderr)
        return 2
    finally:
        executor.shutdown()
        node.destroy_node()
    return 1 if results[-1].stopped else 0


if __name__ == "__main__":
    rclpy.init(args=sys.argv)
    try:
        code = main(remove_ros_args(sys.argv)[1:])
    finally:
        rclpy.try_shutdown()
    sys.exit(code)
