"""Packaging: package.xml and setup.py agree, and a real `colcon build` (colcon-core + colcon-ros from PyPI) installs
the ament_python package the way `ros2 run` / `ros2 launch` expect it.

The colcon build writes only under a temporary directory (--build-base, --install-base, --log-base); the test checks
that it left no build/, install/ or log/ in the checkout. It takes about 1.5 s on the project's 2-core machine.
"""
from __future__ import annotations

import ast
import os
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "agentdress_ros"
EXEC_DEPENDS = {"rclpy", "sensor_msgs", "std_msgs", "shape_msgs", "visualization_msgs"}
CONSOLE_SCRIPTS = {
    "agentdress_node": "agentdress_ros.ros.node:main",
    "agentdress": "agentdress_ros.cli:main",
}
CONFIG_KEYS = {
    "rate_hz",
    "frame_id",
    "joint_state_topic",
    "shape_topic",
    "garments",
    "shape",
    "publish_body",
    "marker_rate_hz",
}


def _setup_call() -> ast.Call:
    """The `setup(...)` call of setup.py, parsed without running it."""
    tree = ast.parse((REPO / "setup.py").read_text(), "setup.py")
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "setup":
            return node
    raise AssertionError("setup.py has no setup(...) call")


def _setup_keyword(name: str):
    for keyword in _setup_call().keywords:
        if keyword.arg == name:
            return keyword.value
    raise AssertionError(f"setup() has no {name}= argument")


def test_package_xml_is_format3_ament_python_with_exec_depends():
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == PACKAGE
    assert root.findtext("version") == "0.1.0"
    assert root.findtext("license") == "Apache-2.0"
    assert root.find("maintainer") is not None and root.find("maintainer").get("email")
    assert root.findtext("export/build_type") == "ament_python"
    assert {e.text for e in root.findall("exec_depend")} >= EXEC_DEPENDS
    assert any("pytest" in (e.text or "") for e in root.findall("test_depend"))


def test_setup_py_console_scripts_and_versions_agree():
    entry_points = ast.literal_eval(_setup_keyword("entry_points"))
    scripts = dict(s.replace(" ", "").split("=", 1) for s in entry_points["console_scripts"])
    assert scripts == CONSOLE_SCRIPTS
    version = ast.literal_eval(_setup_keyword("version"))
    assert version == ET.parse(REPO / "package.xml").getroot().findtext("version")
    init = ast.parse((REPO / PACKAGE / "__init__.py").read_text())
    versions = [
        ast.literal_eval(n.value)
        for n in init.body
        if isinstance(n, ast.Assign) and any(getattr(t, "id", None) == "__version__" for t in n.targets)
    ]
    assert versions == [version]


def test_setup_cfg_puts_scripts_where_ros2_run_looks():
    text = (REPO / "setup.cfg").read_text()
    assert f"script_dir=$base/lib/{PACKAGE}" in text.replace(" ", "")
    assert f"install_scripts=$base/lib/{PACKAGE}" in text.replace(" ", "")
    assert (REPO / "resource" / PACKAGE).is_file()


def test_config_yaml_has_the_documented_node_parameters():
    config = yaml.safe_load((REPO / "config" / "agentdress.yaml").read_text())
    params = config["agentdress_node"]["ros__parameters"]
    assert set(params) >= CONFIG_KEYS
    assert params["rate_hz"] == 90.0 and params["frame_id"] == "agent"
    assert len(params["shape"]) == 6 and all(0.0 <= v <= 1.0 for v in params["shape"])
    assert params["marker_rate_hz"] == 0.0 and params["publish_body"] is False
    # ROS parameters need homogeneous lists: all floats, all strings.
    assert all(isinstance(v, float) for v in params["shape"])
    assert all(isinstance(v, str) for v in params["garments"])


def test_launch_file_is_valid_python_with_a_launch_description():
    launch = REPO / "launch" / "agentdress.launch.py"
    tree = ast.parse(launch.read_text(), str(launch))  # `launch`/`launch_ros` are not on PyPI: parse, don't import
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in functions
    assert "agentdress_node" in launch.read_text() and "agentdress.yaml" in launch.read_text()


def _colcon() -> Path:
    colcon = Path(sys.executable).parent / "colcon"
    if not colcon.exists():
        pytest.skip(f"colcon is not installed beside {sys.executable}: install requirements/test.txt (make setup-test)")
    return colcon


def test_colcon_build_installs_the_ament_python_package(tmp_path):
    colcon = _colcon()
    litter = [REPO / name for name in ("build", "install", "log")]
    existed = {p for p in litter if p.exists()}
    env = dict(os.environ)
    env.pop("AMENT_PREFIX_PATH", None)  # a plain venv: no sourced ROS workspace underneath
    env.pop("COLCON_PREFIX_PATH", None)
    start = time.perf_counter()
    result = subprocess.run(
        [
            str(colcon),
            "--log-base", str(tmp_path / "log"),
            "build",
            "--base-paths", str(REPO),
            "--build-base", str(tmp_path / "build"),
            "--install-base", str(tmp_path / "install"),
            "--event-handlers", "console_direct-",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    seconds = time.perf_counter() - start
    assert result.returncode == 0, f"colcon build failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}"
    assert f"Finished <<< {PACKAGE}" in result.stdout + result.stderr
    print(f"colcon build: {seconds:.1f} s")

    prefix = tmp_path / "install" / PACKAGE
    for script in CONSOLE_SCRIPTS:
        path = prefix / "lib" / PACKAGE / script
        assert path.is_file() and os.access(path, os.X_OK), f"{path} missing or not executable"
    share = prefix / "share" / PACKAGE
    assert (share / "package.xml").read_bytes() == (REPO / "package.xml").read_bytes()
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE).is_file()
    assert (share / "config" / "agentdress.yaml").is_file()
    assert (share / "launch" / "agentdress.launch.py").is_file()

    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    entry_points = next(site.glob(f"{PACKAGE}-*.egg-info")) / "entry_points.txt"
    for name, target in CONSOLE_SCRIPTS.items():
        assert f"{name} = {target}" in entry_points.read_text()
    # Every module of the source tree is installed (a sub-package without __init__.py must not be dropped).
    source = {p.relative_to(REPO).as_posix() for p in (REPO / PACKAGE).rglob("*.py") if "__pycache__" not in p.parts}
    installed = {p.relative_to(site).as_posix() for p in (site / PACKAGE).rglob("*.py")}
    assert source <= installed, f"not installed by colcon: {sorted(source - installed)}"

    # Nothing was written into the checkout.
    assert {p for p in litter if p.exists()} == existed
