"""The web viewer end to end: node, demo and viewer as three processes, the page loaded in headless Chromium.

Chromium renders WebGL in software (SwiftShader through ANGLE), so the page's WebGL path is the one drawn: the page
must report WebGL (not its 2D-canvas fallback), the screenshot must not be blank (the dressed agent covers a few
percent of the window) and two screenshots taken while the demo walks must differ. Skipped, with the reason, when no
Chromium is installed (Debian: `apt-get install -y chromium`); .ci/run installs it or fails.
"""
from __future__ import annotations

import json
import random
import re
import shutil
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="rclpy (ros-jazzy-rclpy wheels, requirements/runtime.txt) is not importable")
from PIL import Image  # noqa: E402

from agentdress_ros.ros.harness import ChildProcess, node_args, ros_env  # noqa: E402

CHROMIUM = next((p for p in (shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")) if p), None)
DOMAIN_ID = random.SystemRandom().randint(1, 200)


def _get_json(url: str):
    with urllib.request.urlopen(url, timeout=5) as response:
        return json.loads(response.read())


def _chromium(url: str, profile, *action) -> subprocess.CompletedProcess:
    """Headless Chromium on `url` with WebGL in software (SwiftShader), doing `action` (--screenshot=..., --dump-dom)
    after a second of virtual time."""
    args = [CHROMIUM, "--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
            "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
            "--disable-sync", f"--user-data-dir={profile}", "--window-size=800,600", "--virtual-time-budget=1000",
            *action, url]
    return subprocess.run(args, capture_output=True, text=True, timeout=90)


def _screenshot(url: str, path, profile) -> np.ndarray:
    proc = _chromium(url, profile, f"--screenshot={path}")
    assert path.is_file(), f"chromium wrote no screenshot ({proc.returncode}):\n{proc.stderr[-2000:]}"
    return np.asarray(Image.open(path).convert("RGB")).astype(np.int16)


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium / chromium-browser / google-chrome on PATH "
                                             "(Debian: apt-get install -y chromium)")
def test_viewer_shows_the_moving_dressed_agent(tmp_path):
    env = ros_env(DOMAIN_ID, str(tmp_path / "ros_log"))
    params = {"garments": ["tshirt", "trousers"], "garment_vertices": ["tshirt:1000", "trousers:1000"],
              "publish_body": True}
    children = {
        "node": ChildProcess(node_args(params), env, tmp_path / "node.log"),
        "demo": ChildProcess([sys.executable, "-m", "agentdress_ros.ros.demo", "--motion", "walk", "--rate", "30"],
                             env, tmp_path / "demo.log"),
        "viewer": ChildProcess([sys.executable, "-m", "agentdress_ros.ros.viewer", "--port", "0"], env,
                               tmp_path / "viewer.log"),
    }
    try:
        viewer = children["viewer"]
        assert viewer.wait_for_output("open http://", 60.0), viewer.output()
        url = re.search(r"open (http://\S+)", viewer.output()).group(1)
        deadline = time.monotonic() + 60.0
        state = {}
        while time.monotonic() < deadline:  # until all three meshes and moving frames arrived
            state = _get_json(url + "state.json")
            meshes = state["meshes"]
            if set(meshes) == {"body", "tshirt", "trousers"} and all(m["frames"] > 5 for m in meshes.values()):
                break
            time.sleep(0.2)
        else:
            pytest.fail(f"viewer state {state}\n" + "\n".join(f"{n}: {c.output()}" for n, c in children.items()))

        page = _chromium(url, tmp_path / "profile0", "--dump-dom")
        info = re.search(r'<div id="info">([^<]*)</div>', page.stdout)
        assert info, f"no status line in the page ({page.returncode}):\n{page.stdout[-2000:]}{page.stderr[-2000:]}"
        assert "(WebGL)" in info.group(1), f"the page did not draw with WebGL: {info.group(1)!r}"
        first = _screenshot(url, tmp_path / "first.png", tmp_path / "profile1")
        # The walk loops every 1.1 s in 33 poses, so a later screenshot can, rarely, land on the same pose: retry
        # (after a random part of the loop) until one differs.
        for attempt in range(3):
            stamp = _get_json(url + "state.json")["meshes"]["tshirt"]["stamp"]
            wait = 0.2 + random.random()
            while _get_json(url + "state.json")["meshes"]["tshirt"]["stamp"] < stamp + wait:  # the agent walked on
                time.sleep(0.05)
            second = _screenshot(url, tmp_path / f"second{attempt}.png", tmp_path / f"profile{attempt + 2}")
            if (np.abs(first - second).sum(axis=2) > 30)[40:].mean() > 0.003:
                break
    finally:
        codes = {name: child.stop() for name, child in children.items()}
    assert all(code == 0 for code in codes.values()), codes

    for image in (first, second):
        background = image[-1, -1]
        covered = (np.abs(image - background).sum(axis=2) > 30)[40:]  # below the status line
        assert covered.mean() > 0.02, f"screenshot nearly blank: {covered.mean():.4f} of the pixels drawn"
        # garment colours present: T-shirt blue and trousers dark grey
        blue = (image[..., 2] > image[..., 0] + 60)[40:]
        assert blue.mean() > 0.003, "no T-shirt (blue) pixels"
    changed = (np.abs(first - second).sum(axis=2) > 30)[40:]
    assert changed.mean() > 0.003, f"the two screenshots barely differ ({changed.mean():.4f}): is the agent moving?"
