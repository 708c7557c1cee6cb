"""Ground-truth drapes: a garment settled on a static, posed, shaped body by NVIDIA newton's VBD cloth solver.

Only this sub-package uses newton (and warp), and only when `drape` runs: importing `agentdress_ros.sim` and
building `DrapeSettings` work without it, so build configurations can be read anywhere. `require_newton` raises
an ImportError that names the install command (`pip install newton==1.8.0`, the project's `build` extra).
"""
from .drape import (
    NEWTON_VERSION,
    DrapeResult,
    DrapeSettings,
    drape,
    membrane_lame,
    push_out_of_body,
    require_newton,
    triangle_stretch,
)

__all__ = [
    "NEWTON_VERSION",
    "DrapeResult",
    "DrapeSettings",
    "drape",
    "membrane_lame",
    "push_out_of_body",
    "require_newton",
    "triangle_stretch",
]
