"""Garments: the project's own templates cut from the body, MakeHuman `.mhclo` import, bindings and regions."""
from .binding import REGION_NAMES, REGIONS, SurfaceBinding, region_weights, vertex_normals
from .garment import Garment
from .mhclo import MhcloBinding, load_mhclo_garment, read_mhclo
from .remesh import cut_by_field, refine_to_vertex_count
from .templates import TEMPLATES, make_garment

__all__ = [
    "REGIONS",
    "REGION_NAMES",
    "TEMPLATES",
    "Garment",
    "MhcloBinding",
    "SurfaceBinding",
    "cut_by_field",
    "load_mhclo_garment",
    "make_garment",
    "read_mhclo",
    "refine_to_vertex_count",
    "region_weights",
    "vertex_normals",
]
