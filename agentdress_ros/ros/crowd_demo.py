"""`agentdress demo --agents N`: a crowd on a plaza for the node's crowd mode, and a walking virtual viewer.

Agent i (`agent_000`, ...) plays a CMU training clip or a procedural motion, with its own body shape, published on
`<agent>/joint_states` (and its shape once, then every few seconds, on `<agent>/body_shape`). Walking motions walk
about the plaza on circles (the clip's own root path is replaced by the circle, the body turned to face its way);
the others stay at their spot facing a random way. `--viewer-walk` publishes a viewer (geometry_msgs/PoseStamped
on `viewer_pose`) walking back and forth across the plaza at eye height, looking where it goes, so levels of detail
change and agents behind it are culled. The test clips of ../shared/mocap/README.md are never used here.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["CrowdPlayer", "TEST_CLIPS", "agent_names", "crowd_main", "training_clips"]

#: ../shared/mocap/README.md: held out for evaluation, never used for building, training or demos.
TEST_CLIPS = frozenset({"02_01", "02_08", "05_07", "05_12", "05_14", "06_04", "06_14", "07_12", "08_10", "09_01"})
WALKING_CLIPS = ("02_02", "03_01", "05_01", "07_01", "07_04", "07_06")
STANDING_CLIPS = ("05_02", "05_03", "06_02", "02_05", "02_10", "02_06")
WALKING_MOTIONS = ("walk",)
STANDING_MOTIONS = ("idle", "wave", "reach", "sweep", "wipe", "squat")
MOCAP = Path(__file__).resolve().parents[3] / "shared" / "mocap" / "cmu"
CLIP_SECONDS = 12.0  # of each clip, sampled at the publishing rate
WALK_SPEED = 1.2  # m/s on the plaza


def agent_names(count: int) -> list[str]:
    return [f"agent_{i:03d}" for i in range(count)]


def training_clips(folder: Path = MOCAP, names=WALKING_CLIPS + STANDING_CLIPS) -> list[Path]:
    """The named clips present in `folder`, never a test clip."""
    return [folder / f"{n}.bvh" for n in names if n not in TEST_CLIPS and (folder / f"{n}.bvh").is_file()]


def _yaw_of(rotvec: np.ndarray) -> float:
    """Heading of a body whose Hips have rotation vector `rotvec` (rest faces -Y): yaw about Z."""
    from scipy.spatial.transform import Rotation

    f = Rotation.from_rotvec(rotvec).apply((0.0, -1.0, 0.0))
    return math.atan2(f[0], -f[1])


@dataclass
class Track:
    """One agent's motion: frames (F, B, 3) at `fps`, in place; its place on the plaza."""

    name: str
    source: str
    rotvecs: np.ndarray
    heights: np.ndarray  # (F,) hips height offset
    yaws: np.ndarray  # (F,) the clip's own heading (removed, replaced by the path's)
    fps: float
    walking: bool
    centre: np.ndarray  # (2,) circle centre (walkers) or spot
    radius: float
    phase: float
    direction: float  # +1 counter-clockwise, -1 clockwise
    facing: float  # yaw of a standing agent
    beta: np.ndarray  # (6,)
    offset: float  # seconds into its clip


class CrowdPlayer:
    """Poses of N agents at time t: `frame(i, t)` -> (rotvecs (B, 3), root_translation (3,))."""

    def __init__(self, count: int, rate_hz: float = 30.0, plaza: float = 30.0, seed: int = 0, near: bool = False,
                 mocap: Path = MOCAP, first_at=None):
        from ..motion.procedural import make_motion
        from ..motion.retarget import load_cmu_motion

        rng = np.random.default_rng(seed)
        clips = {p.stem: p for p in training_clips(mocap)}
        sources = []
        for i in range(count):  # alternate clips and procedural motions, walkers and standers
            cmu = [("cmu", c) for c in (WALKING_CLIPS if i % 2 == 0 else STANDING_CLIPS) if c in clips]
            procedural = [("motion", m) for m in (WALKING_MOTIONS if i % 2 == 0 else STANDING_MOTIONS)]
            pool = [item for pair in zip(cmu, procedural * len(cmu)) for item in pair] or procedural
            sources.append(pool[(i // 2) % len(pool)])
        cache = {}
        for kind, name in set(sources):
            if kind == "cmu":
                motion = load_cmu_motion(clips[name])
                step = max(1, int(round(motion.fps / rate_hz)))
                frames = slice(0, int(CLIP_SECONDS * motion.fps), step)
                rotvecs, translation, fps = motion.rotvecs[frames], motion.root_translation[frames], motion.fps / step
            else:
                motion = make_motion(name, fps=rate_hz)
                rotvecs, translation, fps = motion.rotvecs, motion.root_translation, motion.fps
            yaws = np.array([_yaw_of(r[0]) for r in rotvecs])
            cache[(kind, name)] = (np.array(rotvecs), np.array(translation)[:, 2], yaws, fps)
        self.tracks = []
        for i, (kind, name) in enumerate(sources):
            rotvecs, heights, yaws, fps = cache[(kind, name)]
            walking = name in WALKING_CLIPS or name in WALKING_MOTIONS
            if near:  # every agent within 3 m of the origin
                centre = rng.uniform(-2.0, 2.0, 2)
            else:
                centre = rng.uniform(-plaza / 2, plaza / 2, 2)
            beta = np.array([rng.uniform(0.1, 0.9), rng.uniform(0.5, 0.85), rng.uniform(0.2, 0.8),
                             rng.uniform(0.15, 0.85), rng.uniform(0.2, 0.8), 0.5])
            self.tracks.append(Track(f"{kind}:{name}", name, rotvecs, heights, yaws, fps, walking and not near,
                                     centre, rng.uniform(2.0, 6.0), rng.uniform(0, 2 * math.pi),
                                     rng.choice([-1.0, 1.0]), rng.uniform(-math.pi, math.pi), beta,
                                     rng.uniform(0, len(rotvecs) / fps)))
        if first_at is not None:  # agent 0 stands at a given spot (e.g. in front of a fixed viewer)
            self.tracks[0].walking, self.tracks[0].centre = False, np.asarray(first_at, dtype=np.float64)

    def frames(self, t: float):
        """Every agent at time t: rotvecs (N, B, 3), root translations (N, 3) (one vectorised pass)."""
        from scipy.spatial.transform import Rotation

        n = len(self.tracks)
        rotvecs = np.empty((n,) + self.tracks[0].rotvecs.shape[1:])
        roots, turns = np.empty((n, 3)), np.empty(n)
        for i, track in enumerate(self.tracks):
            k = int((t + track.offset) * track.fps) % len(track.rotvecs)
            rotvecs[i] = track.rotvecs[k]
            if track.walking:
                angle = track.phase + track.direction * WALK_SPEED * t / track.radius
                roots[i, :2] = track.centre + track.radius * np.array([math.cos(angle), math.sin(angle)])
                heading = math.atan2(-track.direction * math.sin(angle), -track.direction * math.cos(angle))
            else:
                roots[i, :2], heading = track.centre, track.facing
            roots[i, 2] = track.heights[k]
            turns[i] = heading - track.yaws[k]
        turn = Rotation.from_rotvec(np.outer(turns, (0.0, 0.0, 1.0)))
        rotvecs[:, 0] = (turn * Rotation.from_rotvec(rotvecs[:, 0])).as_rotvec()
        return rotvecs, roots

    def frame(self, i: int, t: float):
        """Agent i at time t: (rotvecs (B, 3), root_translation (3,))."""
        rotvecs, roots = self.frames(t)
        return rotvecs[i], roots[i]


def viewer_pose(t: float, plaza: float = 30.0, speed: float = 1.4):
    """A viewer walking back and forth along the x axis across the plaza, eyes at 1.6 m, looking where it goes:
    (position (3,), quaternion (x, y, z, w))."""
    span = plaza + 10.0
    s = (speed * t) % (2 * span)
    forward = s < span
    x = -span / 2 + (s if forward else 2 * span - s)
    yaw = 0.0 if forward else math.pi
    return np.array([x, -2.0, 1.6]), (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agentdress demo --agents N", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--agents", type=int, required=True, help="number of agents")
    parser.add_argument("--rate", type=float, default=30.0, help="JointState rate per agent, Hz (default 30)")
    parser.add_argument("--plaza", type=float, default=30.0, help="side of the square plaza, m (default 30)")
    parser.add_argument("--near", action="store_true", help="every agent within 3 m of the origin, standing")
    parser.add_argument("--viewer-walk", action="store_true", help="publish a viewer walking across the plaza")
    parser.add_argument("--viewer-at", type=float, nargs=4, metavar=("X", "Y", "Z", "YAW"), default=None,
                        help="publish a fixed viewer pose instead (yaw 0 looks along +x)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: run forever)")
    return parser


def crowd_main(argv=None) -> int:
    """Publish the crowd until Ctrl-C (or --duration). ROS args after --ros-args go to rclpy."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32MultiArray

    from ..motion.joint_names import JOINT_NAMES
    from .messages import SerializedJointState
    from .spin import run_publisher

    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    args = build_parser().parse_args(argv[: len(argv) - len(ros_args)])
    if args.agents < 1 or not (args.rate > 0 and math.isfinite(args.rate)):
        print("agentdress demo: error: --agents must be >= 1 and --rate positive", file=sys.stderr)
        return 2
    first_at = None
    if args.viewer_at is not None:  # the first agent stands 2.5 m in front of the fixed viewer
        x, y, _, yaw = args.viewer_at
        first_at = (x + 2.5 * math.cos(yaw), y + 2.5 * math.sin(yaw))
    player = CrowdPlayer(args.agents, args.rate, args.plaza, args.seed, args.near, first_at=first_at)
    names = agent_names(args.agents)
    rclpy.init(args=["agentdress_crowd_demo", *ros_args])
    node = rclpy.create_node("agentdress_crowd_demo")
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
    joint_pubs = [node.create_publisher(JointState, f"{n}/joint_states", qos) for n in names]
    shape_pubs = [node.create_publisher(Float32MultiArray, f"{n}/body_shape", 1) for n in names]
    viewer_pub = node.create_publisher(PoseStamped, "viewer_pose", 1)
    joint_state = SerializedJointState("world", JOINT_NAMES)  # the driver's own cost stays off the node's core
    start = time.monotonic()
    state = {"last_shape": -1e9}

    def publish():
        t = time.monotonic() - start
        if args.duration and t > args.duration:
            raise SystemExit(0)
        rotvecs, roots = player.frames(t)
        positions = np.concatenate([rotvecs.reshape(len(names), -1), roots], axis=1)
        clock = node.get_clock()
        for i, pub in enumerate(joint_pubs):
            now = clock.now()  # each stamped as it is sent: latency counts from here
            pub.publish(joint_state.set(positions[i], now.nanoseconds))
        stamp = now.to_msg()
        if t - state["last_shape"] >= 5.0:  # shapes now and then (reliable, depth 1: a late node still gets one)
            state["last_shape"] = t
            for i, pub in enumerate(shape_pubs):
                pub.publish(Float32MultiArray(data=player.tracks[i].beta.astype(np.float32).tolist()))
        if args.viewer_walk or args.viewer_at is not None:
            if args.viewer_walk:
                position, q = viewer_pose(t, args.plaza)
            else:
                x, y, z, yaw = args.viewer_at
                position, q = (x, y, z), (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
            pose = PoseStamped()
            pose.header.stamp, pose.header.frame_id = stamp, "world"
            pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = (float(v) for v in position)
            (pose.pose.orientation.x, pose.pose.orientation.y, pose.pose.orientation.z,
             pose.pose.orientation.w) = (float(v) for v in q)
            viewer_pub.publish(pose)

    node.create_timer(1.0 / args.rate, publish)
    kinds = sorted({t.name for t in player.tracks})
    print(f"agentdress demo: publishing {args.agents} agents at {args.rate:g} Hz ({', '.join(kinds)})"
          + (", viewer walking" if args.viewer_walk else ""), flush=True)
    return run_publisher(node)


if __name__ == "__main__":
    sys.exit(crowd_main())
