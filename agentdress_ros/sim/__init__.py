"""Ground-truth drapes and sequences: a garment simulated on a posed (or moving), shaped body by NVIDIA newton's VBD cloth solver.

Only this sub-package uses newton (and warp), and only when `drape` runs: importing `agentdress_ros.sim` and
building `DrapeSettings` work without it, so build configurations can be read anywhere. `require_newton` raises
an ImportError that names the install command (`pip install newton==1.8.0`, the project's `build` extra).
"""
from .cloth import ClothSim
from .drape import DrapeResult, drape, push_out_of_body, triangle_stretch
from .settings import NEWTON_VERSION, DrapeSettings, membrane_lame, require_newton

__all__ = [
    "ClothSim",
    "NEWTON_VERSION",
    "DrapeResult",
    "DrapeSettings",
    "drape",
    "membrane_lame",
    "push_out_of_body",
    "require_newton",
    "triangle_stretch",
]
