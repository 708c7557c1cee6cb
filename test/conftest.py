"""Shared fixtures: the body model (built once per session) and the location of ../shared test data."""
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"


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
