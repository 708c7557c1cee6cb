"""`agentdress demo`: a JointState player so the node has an agent to dress.

Plays a procedural motion (default `walk`) or a CMU .bvh clip in real time, looping, as sensor_msgs/JointState
(`<Bone>_rx/_ry/_rz`, `Hips_tx/_ty/_tz`, stamped with the wall clock), and optionally sweeps the body shape slowly
on the shape topic (std_msgs/Float32MultiArray, 1 Hz).
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from ..body import REFERENCE_SHAPE

__all__ = ["JointStatePlayer", "build_parser", "demo_main", "load_clip", "sweep_shape"]


def load_clip(source: str, rate_hz: float):
    """A procedural motion name (sampled at `rate_hz` over one period) or a .bvh path (at the clip's fps) -> Motion
    with rotvecs (F, B, 3), root_translation (F, 3), fps."""
    from ..motion.procedural import make_motion, motion_names
    from ..motion.retarget import load_cmu_motion

    if source.lower().endswith(".bvh"):
        return load_cmu_motion(source)
    if source not in motion_names():
        raise ValueError(f"unknown motion {source!r}: give a .bvh file or one of {', '.join(motion_names())}")
    return make_motion(source, fps=rate_hz)


def sweep_shape(t: float, period: float) -> np.ndarray:
    """Body shape (6,) at time t of a slow sweep: weight and gender swing around the reference shape."""
    phase = 2.0 * math.pi * t / period
    beta = np.array(REFERENCE_SHAPE, dtype=np.float64)
    beta[3] = 0.5 + 0.35 * math.sin(phase)  # weight
    beta[0] = 0.5 + 0.5 * math.sin(0.5 * phase)  # gender
    return np.clip(beta, 0.0, 1.0)


class JointStatePlayer:
    """Frame lookup of a looping clip in real time: `frame(t)` -> (rotvecs (B, 3), root_translation (3,))."""

    def __init__(self, motion, translate: bool = True):
        self.motion, self.translate = motion, translate

    @property
    def duration(self) -> float:
        return len(self.motion.rotvecs) / self.motion.fps

    def frame(self, t: float):
        index = int(t * self.motion.fps) % len(self.motion.rotvecs)
        translation = self.motion.root_translation[index] if self.translate else np.zeros(3)
        return self.motion.rotvecs[index], translation


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agentdress demo", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--motion", default="walk", help="procedural motion name or a CMU .bvh file (default walk)")
    parser.add_argument("--rate", type=float, default=60.0, help="JointState publishing rate, Hz (default 60)")
    parser.add_argument("--topic", default="joint_states", help="JointState topic")
    parser.add_argument("--shape-topic", default="body_shape", help="body shape topic")
    parser.add_argument("--shape-sweep", type=float, default=0.0, metavar="PERIOD",
                        help="sweep the body shape with this period in seconds (0: off; publishes the reference "
                             "shape once at start otherwise)")
    parser.add_argument("--no-translation", action="store_true", help="keep the root in place")
    parser.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: run forever)")
    return parser


def demo_main(argv=None) -> int:
    """`agentdress demo [--motion walk|clip.bvh] [--rate 60] [--shape-sweep 20] [--duration 0] ...` (ROS args
    after --ros-args are passed to rclpy). Returns the exit status."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32MultiArray

    from ..motion.joint_names import JOINT_NAMES
    from .spin import run_publisher

    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    args = build_parser().parse_args(argv[: len(argv) - len(ros_args)])
    if not (args.rate > 0 and math.isfinite(args.rate)):
        print(f"agentdress demo: error: --rate must be positive, got {args.rate}", file=sys.stderr)
        return 2
    try:
        player = JointStatePlayer(load_clip(args.motion, args.rate), translate=not args.no_translation)
    except (ValueError, OSError) as error:
        print(f"agentdress demo: error: {error}", file=sys.stderr)
        return 2

    rclpy.init(args=["agentdress_demo", *ros_args])
    node = rclpy.create_node("agentdress_demo")
    joint_pub = node.create_publisher(JointState, args.topic, QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
    shape_pub = node.create_publisher(Float32MultiArray, args.shape_topic, 1)
    names = list(JOINT_NAMES)
    start = time.monotonic()
    state = {"last_shape": -1e9, "frames": 0}

    def publish_pose():
        t = time.monotonic() - start
        if args.duration and t > args.duration:
            raise SystemExit(0)
        rotvecs, translation = player.frame(t)
        msg = JointState()
        msg.header.stamp = node.get_clock().now().to_msg()
        msg.header.frame_id = "agent"
        msg.name = names
        msg.position = np.concatenate([rotvecs.reshape(-1), translation]).tolist()
        joint_pub.publish(msg)
        state["frames"] += 1
        if args.shape_sweep > 0 and t - state["last_shape"] >= 1.0:
            state["last_shape"] = t
            shape_pub.publish(Float32MultiArray(data=sweep_shape(t, args.shape_sweep).astype(np.float32).tolist()))

    node.create_timer(1.0 / args.rate, publish_pose)
    print(f"agentdress demo: publishing {args.motion} ({player.duration:.1f} s loop) on {args.topic} at "
          f"{args.rate:g} Hz" + (f", shape sweep every {args.shape_sweep:g} s" if args.shape_sweep > 0 else ""),
          flush=True)
    return run_publisher(node)


if __name__ == "__main__":
    sys.exit(demo_main())
