"""Process harness shared by the tests and `agentdress bench node`: the node (and friends) as child processes on a
private ROS domain, and a private rclpy context in this process. Every wait is bounded and waits on a condition.

Environment of a run: a random ROS_DOMAIN_ID in 1-101 (so parallel runs do not hear each other; on Linux, ids above
101 put DDS' ports into the ephemeral range, where another socket may already hold one), loopback-only discovery
(ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST; a late participant is discovered after ~3 s), logs in a temp dir.
"""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "agentdress.yaml"

__all__ = ["ChildProcess", "node_args", "random_domain", "ros_env", "ros_node", "spin_until"]

SAFE_DOMAIN_IDS = 101  # 1..101: DDS ports below Linux' ephemeral range (32768-60999)


def random_domain() -> int:
    """A random ROS_DOMAIN_ID whose DDS ports no ephemeral socket can hold."""
    return random.SystemRandom().randint(1, SAFE_DOMAIN_IDS)


def ros_env(domain_id: int | None = None, log_dir: str | None = None) -> dict:
    """This process' environment with a private domain and loopback discovery."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id if domain_id is not None else random_domain())
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_LOG_DIR"] = log_dir or tempfile.mkdtemp(prefix="agentdress_roslog_")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def node_args(params: dict | None = None, params_file: Path | None = CONFIG) -> list[str]:
    """`python -m agentdress_ros.ros.node --ros-args ...` with `params` as -p overrides (lists as YAML)."""
    args = [sys.executable, "-m", "agentdress_ros.ros.node", "--ros-args"]
    if params_file is not None:
        args += ["--params-file", str(params_file)]
    for name, value in (params or {}).items():
        if isinstance(value, bool):
            text = "true" if value else "false"
        elif isinstance(value, (list, tuple)):
            text = "[" + ",".join(f"'{v}'" if isinstance(v, str) else repr(float(v)) for v in value) + "]"
        else:
            text = str(value)
        args += ["-p", f"{name}:={text}"]
    return args


class ChildProcess:
    """A child process with stdout+stderr in a file; `stop()` sends SIGINT, then kills after `grace` seconds."""

    def __init__(self, args, env, log_path: Path, cwd=ROOT):
        self.args, self.log_path = list(args), Path(log_path)
        self._log = open(self.log_path, "w+")
        self.proc = subprocess.Popen(self.args, env=env, stdout=self._log, stderr=subprocess.STDOUT, cwd=cwd,
                                     start_new_session=True)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def output(self, tail: int = 4000) -> str:
        if not self._log.closed:  # after stop() the file is complete on disk
            self._log.flush()
        return self.log_path.read_text(errors="replace")[-tail:]

    def wait_for_output(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output(100_000):
                return True
            if self.proc.poll() is not None:
                return text in self.output(100_000)
            time.sleep(0.05)
        return False

    def stop(self, grace: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode


@contextmanager
def ros_node(name: str, domain_id: int):
    """(node, executor) in a private rclpy context on `domain_id`."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = rclpy.create_node(name, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)


def spin_until(executor, done, timeout: float) -> bool:
    """Spin until done() or the timeout; returns done()."""
    deadline = time.monotonic() + timeout
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.02)
    return bool(done())
