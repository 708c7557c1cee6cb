"""Shared fixtures and helpers: the body model and the shipped T-shirt database (each read once per session), the
location of ../shared test data, DDS domain ids unique across the xdist workers, warp's kernels compiled once, and
the node start-up, parameter and QoS helpers of the tests that talk to a live node over DDS.

`make test` runs the suite on two xdist workers, a file at a time per worker (--dist loadfile: a module's fixtures,
such as the tiny build or the quick evaluation, are made once); files are handed out slowest first (SLOWEST_FIRST)
so that both workers finish together."""
import os
import random
from contextlib import contextmanager
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(__file__).resolve().parents[2] / "shared"
DATA = ROOT / "data"
TSHIRT_DATABASE = DATA / "tshirt_default.h5"
TSHIRT_PACK = DATA / "tshirt_sequences.npz"

# The files that take longest, longest first: a worker picks the next file when it finishes one, so the long ones
# start at once and the short ones fill the end. The second is one that drapes nothing: while the first worker
# compiles newton's kernels (80 s on a cold warp cache, under a lock), the second has its own work instead of
# waiting for that lock.
SLOWEST_FIRST = ("test_build.py", "test_viewer.py", "test_eval.py", "test_sim.py", "test_faults.py",
                 "test_kdsm.py", "test_regressor.py", "test_node.py", "test_crowd_node.py", "test_shape_residual.py",
                 "test_node_bad_input.py", "test_santesteban.py", "test_recurrent.py", "test_packaging.py")


def pytest_collection_modifyitems(items):
    rank = {name: k for k, name in enumerate(SLOWEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file's own order is kept


def shared_path(*parts) -> Path:
    """A path under ../shared; a test that needs it fails, naming the path, when that data is absent (it is part of
    the test set, not an optional extra: a missing checkout of it must not pass as skipped tests)."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.fail(f"test data {path} is absent: the tests read ../shared beside the checkout (mocap clips, "
                    "reference garments); put it there", pytrace=False)
    return path


@pytest.fixture(scope="session")
def body():
    from agentdress_ros.body import AnnyBody

    return AnnyBody()


@pytest.fixture(scope="session")
def database():
    """The shipped T-shirt database (data/tshirt_default.h5)."""
    from agentdress_ros.engine.database import read_database

    return read_database(TSHIRT_DATABASE)


# ------------------------------------------------------------------------------------------ warp's kernel cache


@pytest.fixture(scope="session")
def warp_kernels():
    """newton's cloth kernels compiled into warp's kernel cache (a three-frame drape of a small sheet) before a test
    drapes. Each xdist worker does this under one lock: the first compiles while the other waits, then loads them;
    a build's dask workers started afterwards load them too, instead of compiling the same kernels side by side
    (warp's cache stays consistent either way: each process compiles in its own folder and renames it in)."""
    import fcntl

    import numpy as np

    pytest.importorskip("newton", reason="newton (the build extra, requirements/build.txt) is not installed")
    import warp

    from agentdress_ros.sim import DrapeSettings, drape

    warp.init()
    lock_path = Path(warp.config.kernel_cache_dir) / "agentdress_tests.lock"
    with open(lock_path, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        grid = np.stack(np.meshgrid(np.linspace(0.0, 0.2, 4), np.linspace(0.0, 0.2, 4)), axis=-1).reshape(-1, 2)
        sheet = np.column_stack([grid, np.full(len(grid), 0.05)])
        faces = np.array([[r * 4 + c, r * 4 + c + 1, (r + 1) * 4 + c + 1] for r in range(3) for c in range(3)]
                         + [[r * 4 + c, (r + 1) * 4 + c + 1, (r + 1) * 4 + c] for r in range(3) for c in range(3)])
        tet = np.array([[0.0, 0.0, -0.1], [0.3, 0.0, -0.1], [0.0, 0.3, -0.1], [0.0, 0.0, 0.02]])
        tet_faces = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
        drape(sheet, faces, tet, tet_faces, DrapeSettings(max_frames=3, min_frames=1))


# ------------------------------------------------------------------------------------------------ DDS domains

# 0 is the default domain (a running `make run` uses it); above 101 a participant's ports can reach the range
# Linux hands out as ephemeral ports.
DOMAIN_IDS = 101
_DOMAIN_OFFSET = "AGENTDRESS_TEST_DOMAIN_OFFSET"


def pytest_configure(config):
    # One random offset per run, drawn before the xdist workers start (they inherit it): two runs on one machine
    # rarely meet, the workers of one run never do.
    os.environ.setdefault(_DOMAIN_OFFSET, str(random.SystemRandom().randrange(DOMAIN_IDS)))


@pytest.fixture(scope="session")
def ros_domain(request):
    """new_domain() -> a DDS domain id in 1-101 that no other call in this run returns: each xdist worker draws from
    its own block of the 101 ids (`make test`: two workers, 50 each)."""
    worker = getattr(request.config, "workerinput", None)
    index, count = (int(worker["workerid"].removeprefix("gw")), int(worker["workercount"])) if worker else (0, 1)
    block = DOMAIN_IDS // count
    offset = int(os.environ[_DOMAIN_OFFSET])
    ids = iter([1 + (offset + index * block + k) % DOMAIN_IDS for k in range(block)])

    def new_domain() -> int:
        domain = next(ids, None)
        if domain is None:
            raise RuntimeError(f"this worker's {block} DDS domain ids are used up")
        return domain

    return new_domain


# ------------------------------------------------------------------------------------- a live node over DDS


def qos(reliability: str, depth: int, transient_local: bool = False):
    """A KEEP_LAST QoS profile: reliability 'best_effort' (the node's clouds) or 'reliable'; transient_local for
    the latched topology (the mesh topics)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.BEST_EFFORT if reliability == "best_effort"
                      else ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if transient_local else DurabilityPolicy.VOLATILE)


@contextmanager
def running_node(folder: Path, domain: int, params: dict | None = None, ready: str = "garment models ready",
                 timeout: float = 120.0, args: list | None = None):
    """agentdress_node (with `params` over config/agentdress.yaml, or the command `args`) as a child process on
    `domain`, its log and ROS logs in `folder`; fails with the node's output when `ready` is not printed within
    `timeout` seconds, and when the node does not exit with status 0 on SIGINT afterwards."""
    from agentdress_ros.ros.harness import ChildProcess, node_args, ros_env

    folder.mkdir(parents=True, exist_ok=True)
    child = ChildProcess(args or node_args(params), ros_env(domain, str(folder / "ros_log")), folder / "node.log")
    try:
        if not child.wait_for_output(ready, timeout=timeout):
            pytest.fail(f"node did not start:\n{child.output()}")
        yield child
    finally:
        rc = child.stop()
    assert rc == 0, f"node exited with {rc} on SIGINT:\n{child.output()}"


def set_parameters(node, executor, **values):
    """Set the running node's parameters through its set_parameters service; its SetParametersResult list."""
    return call_node_service(node, executor, "set_parameters", parameters=values).results


def call_node_service(node, executor, service: str, timeout: float = 30.0, parameters: dict | None = None,
                      names: list | None = None):
    """The answer of /agentdress_node/<service> (set_parameters with `parameters`, get_parameters with `names`)."""
    from rcl_interfaces.srv import GetParameters, SetParameters
    from rclpy.parameter import Parameter

    from agentdress_ros.ros.harness import spin_until

    if service == "set_parameters":
        kind, request = SetParameters, SetParameters.Request(
            parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in parameters.items()])
    else:
        kind, request = GetParameters, GetParameters.Request(names=list(names))
    client = node.create_client(kind, f"/agentdress_node/{service}")
    try:
        assert client.wait_for_service(timeout_sec=timeout), f"/agentdress_node/{service} is not offered"
        future = client.call_async(request)
        assert spin_until(executor, future.done, timeout), f"{service} did not answer"
        return future.result()
    finally:
        node.destroy_client(client)


def assert_no_learning_library_after(code: str) -> None:
    """Run `code` (Python that loads and runs a trained model) in a fresh interpreter: it must succeed without
    importing scikit-learn, torch or JAX (offline tools only)."""
    import subprocess
    import sys

    check = subprocess.run([sys.executable, "-c", code + "\nimport sys\nprint(sorted(m for m in sys.modules if "
                            "m.split('.')[0] in ('sklearn', 'torch', 'jax')))\n"],
                           capture_output=True, text=True, timeout=300)
    assert check.returncode == 0, check.stderr[-2000:]
    assert check.stdout.strip().splitlines()[-1] == "[]", check.stdout[-500:]


def run_training_command(module: str, *args) -> dict:
    """`python -m <module> <args>` (a training command that prints a JSON report last); its report."""
    import json
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", module, *map(str, args)], capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(result.stdout.strip().splitlines()[-1])
