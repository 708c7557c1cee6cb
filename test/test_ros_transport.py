"""Real DDS between two processes with the ROS 2 Jazzy wheels from PyPI (rclpy + Fast DDS), no mocks.

A publisher runs in a child Python process (the script below, run with `python -c`); this pytest process subscribes
through its own rclpy context. The module uses a ROS_DOMAIN_ID of its own (conftest's ros_domain: no other test of the
run, nor usually another run, on it) and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST so discovery stays on the loopback interface.
Every wait is bounded. The tests skip only when rclpy cannot be imported.

Environment: nothing has to be set by hand. The ros-wheels-bootstrapper wheel's .pth file re-executes each Python
started from the venv once with LD_LIBRARY_PATH pointing at the wheels' shared libraries, and the child inherits that
environment; the default middleware is rmw_fastrtps_cpp.
"""
from __future__ import annotations

import os
import selectors
import subprocess
import sys
import time
from contextlib import contextmanager

import pytest

rclpy = pytest.importorskip("rclpy", reason="rclpy (ros-jazzy-rclpy wheels, requirements/runtime.txt) is not importable")

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from agentdress_ros.ros import harness  # noqa: E402

JOINT_NAMES = ["Hips_tx", "Hips_ty", "Hips_tz", "LeftArm_rx", "LeftArm_ry", "LeftArm_rz"]
POSITIONS = [0.125, -0.5, 0.9375, 1.0e-3, -3.0, 0.333333]
GRID = 110  # the published mesh: a GRID x GRID vertex sheet (12,100 vertices, 23,762 triangles: garment-sized)

CHILD = r"""
import sys, time
import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

mode, topic, deadline = sys.argv[1], sys.argv[2], time.monotonic() + float(sys.argv[3])
rclpy.init()
node = rclpy.create_node("agentdress_test_publisher")

if mode == "joint_state":
    from sensor_msgs.msg import JointState
    names, positions = sys.argv[4].split(","), [float(v) for v in sys.argv[5].split(",")]
    publisher = node.create_publisher(JointState, topic, 10)
    while publisher.get_subscription_count() == 0:  # wait for the test's subscriber to be matched
        if time.monotonic() > deadline:
            sys.exit("no subscriber matched before the deadline")
        time.sleep(0.02)
    for i in range(5):
        msg = JointState()
        msg.header.stamp = node.get_clock().now().to_msg()
        msg.header.frame_id = f"agent/{i}"
        msg.name, msg.position = names, positions
        msg.velocity = [float(i)] * len(names)
        publisher.publish(msg)
        time.sleep(0.05)
    time.sleep(0.5)  # let reliable delivery finish before the participant goes away
else:  # "mesh": publish once on a reliable transient-local topic, before anybody subscribes
    from geometry_msgs.msg import Point
    from shape_msgs.msg import Mesh, MeshTriangle
    grid = int(sys.argv[4])
    qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publisher = node.create_publisher(Mesh, topic, qos)
    mesh = Mesh()
    mesh.vertices = [Point(x=0.01 * i, y=0.02 * j, z=1.5) for j in range(grid) for i in range(grid)]
    for j in range(grid - 1):
        for i in range(grid - 1):
            a = j * grid + i
            mesh.triangles.append(MeshTriangle(vertex_indices=[a, a + 1, a + grid]))
            mesh.triangles.append(MeshTriangle(vertex_indices=[a + 1, a + grid + 1, a + grid]))
    publisher.publish(mesh)
    print(f"PUBLISHED subscribers={publisher.get_subscription_count()}", flush=True)
    sys.stdin.read()  # stay alive (holding the transient-local sample) until the test closes our stdin
    if time.monotonic() > deadline:
        sys.exit("the test took longer than the deadline")
node.destroy_node()
rclpy.shutdown()
"""


@pytest.fixture(scope="module")
def domain(ros_domain):
    return ros_domain()


@pytest.fixture(scope="module")
def ros_env(tmp_path_factory, domain):
    """The environment of both processes: this run's domain, loopback-only discovery, logs in a temp dir."""
    settings = {
        "ROS_DOMAIN_ID": str(domain),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_LOG_DIR": str(tmp_path_factory.mktemp("ros_log")),
    }
    saved = {key: os.environ.get(key) for key in settings}
    os.environ.update(settings)
    try:
        yield dict(os.environ)
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@contextmanager
def ros_node(name: str, domain: int):
    """A node in a private rclpy context (so other tests' use of the global context does not interfere)."""
    with harness.ros_node(name, domain) as pair:
        yield pair


def spin_until(executor, done, timeout: float) -> float:
    start = time.monotonic()
    while not done() and time.monotonic() - start < timeout:
        executor.spin_once(timeout_sec=0.05)
    return time.monotonic() - start


def start_child(env, tmp_path, *args, stdin=None):
    stderr = open(tmp_path / "child_stderr.txt", "w+")
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, *map(str, args)],
        env=env,
        stdin=stdin,
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
    )
    return proc, stderr


def child_stderr(stderr) -> str:
    stderr.flush()
    stderr.seek(0)
    return stderr.read()[-3000:]


def test_joint_state_crosses_processes(ros_env, domain, tmp_path):
    topic = f"agentdress_test_joint_states_{os.getpid()}"
    received = []
    with ros_node("agentdress_test_subscriber", domain) as (node, executor):
        from sensor_msgs.msg import JointState

        node.create_subscription(JointState, topic, received.append, 10)
        proc, stderr = start_child(
            ros_env, tmp_path, "joint_state", topic, 20.0, ",".join(JOINT_NAMES), ",".join(map(repr, POSITIONS))
        )
        try:
            waited = spin_until(executor, lambda: len(received) >= 5, timeout=20.0)
            rc = proc.wait(timeout=20.0)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert rc == 0, f"publisher process failed ({rc}):\n{child_stderr(stderr)}"
    assert received, f"no JointState arrived within {waited:.1f} s on domain {domain}:\n{child_stderr(stderr)}"
    for msg in received:
        assert list(msg.name) == JOINT_NAMES
        assert list(msg.position) == POSITIONS  # float64 on the wire: bit-exact
        assert msg.header.frame_id.startswith("agent/")
        assert msg.header.stamp.sec > 0
    assert len(received) == 5, f"reliable QoS with a matched subscriber lost messages: got {len(received)} of 5"
    assert [msg.velocity[0] for msg in received] == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_transient_local_mesh_reaches_a_late_subscriber(ros_env, domain, tmp_path):
    """The topology (shape_msgs/Mesh) is published once; a display client that subscribes later still gets it.

    Measured here: with LOCALHOST discovery the late participant is discovered after ~3 s (0.24 s with the default
    SUBNET range, which would send multicast off the loopback interface), so the wait is bounded at 20 s.
    """
    topic = f"agentdress_test_mesh_{os.getpid()}"
    proc, stderr = start_child(ros_env, tmp_path, "mesh", topic, 60.0, GRID, stdin=subprocess.PIPE)
    try:
        # Wait (bounded) until the child says it has published: only then does the subscriber exist.
        selector = selectors.DefaultSelector()
        selector.register(proc.stdout, selectors.EVENT_READ)
        line = proc.stdout.readline() if selector.select(timeout=30.0) else ""
        assert line.startswith("PUBLISHED"), f"publisher did not report ({line!r}):\n{child_stderr(stderr)}"
        assert line.split("subscribers=")[1].strip() == "0", "the subscriber was not late"
        time.sleep(0.5)  # later still: the sample has been sitting in the writer's history

        received = []
        with ros_node("agentdress_test_late_subscriber", domain) as (node, executor):
            from shape_msgs.msg import Mesh

            qos = QoSProfile(
                depth=1,
                history=HistoryPolicy.KEEP_LAST,
                reliability=ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL,
            )
            node.create_subscription(Mesh, topic, received.append, qos)
            waited = spin_until(executor, lambda: bool(received), timeout=20.0)
        print(f"late subscriber waited {waited:.2f} s")
        assert received, f"late subscriber got no Mesh within {waited:.1f} s:\n{child_stderr(stderr)}"
        proc.stdin.close()
        assert proc.wait(timeout=20.0) == 0, child_stderr(stderr)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()

    mesh = received[0]
    assert len(received) == 1
    assert len(mesh.vertices) == GRID * GRID
    assert len(mesh.triangles) == 2 * (GRID - 1) ** 2
    last = mesh.vertices[-1]
    assert (last.x, last.y, last.z) == (0.01 * (GRID - 1), 0.02 * (GRID - 1), 1.5)
    assert list(mesh.triangles[0].vertex_indices) == [0, 1, GRID]
    assert list(mesh.triangles[-1].vertex_indices) == [GRID * GRID - GRID - 1, GRID * GRID - 1, GRID * GRID - 2]
