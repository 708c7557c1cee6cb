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
