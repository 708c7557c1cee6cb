"""Shared fixtures: the body model (built once per session) and the location of ../shared test data."""
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"


def shared_path(*parts) -> Path:
    """A path under ../shared, or skip the test with the reason when that data is absent."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"test data {path} is absent (the project reads ../shared beside the checkout)")
    return path


@pytest.fixture(scope="session")
def body():
    from agentdress_ros.body import AnnyBody

    return AnnyBody()
