"""`python -m agentdress_ros.ros.warm_kernels`: compile and cache the node's numba kernels ahead of its first start.

Every kernel is compiled once and cached beside its module (numba's `cache=True`), but a fresh checkout has no cache:
the first node to start compiles them all (about 30 CPU-seconds), and several processes that start together (the
node, the demo, the viewer, a test's own process) each compile the same kernels side by side. This runs the
node's default frame path once - the shipped T-shirt and trousers with the body, one Loop round, layering, the
edge push, the messages - so that later processes load the kernels instead. `make test` runs it beside its
installs.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "data"


def warm(body=None) -> float:
    """Run one frame of the default node path; the CPU seconds it took."""
    from ..body import AnnyBody
    from ..engine.config import EngineKnobs
    from .messages import SerializedBones, make_point_cloud, set_cloud_vertices
    from .params import default_engine
    from .runtime import SceneSpec, build_model_set
    from ..scene.garments import GarmentSpec

    start = time.process_time()
    body = body if body is not None else AnnyBody()
    specs = tuple(GarmentSpec(name, None, str(DATA / f"{name}_default.h5"), EngineKnobs.of(**default_engine(name)))
                  for name in ("tshirt", "trousers") if (DATA / f"{name}_default.h5").is_file())
    models = build_model_set(SceneSpec(specs, True, (0.5,) * 6, display_subdivision=1), body).models
    cloud, bones = make_point_cloud(), SerializedBones("agent", body.n_bones)
    pose = np.zeros((body.n_bones, 3))
    for model in models.values():
        set_cloud_vertices(cloud, model.synthesize(pose, np.zeros(3)))
        transforms = getattr(model, "transforms", None)
        if transforms is not None:
            bones.set(transforms, 0)
    return time.process_time() - start


def main() -> int:
    seconds = warm()
    print(f"numba kernels compiled or loaded in {seconds:.1f} CPU-s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
