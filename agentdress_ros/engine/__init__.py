"""Runtime engine: database reader, pose models, synthesis (Eq. 4, 7-8), refinement (Eq. 9-10).

Never imports rclpy, newton, agentdress_ros.sim or agentdress_ros.offline. Names are imported lazily so that
`agentdress_ros.engine.database` (used by the build stage) stays light.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "Engine": ".engine",
    "ShapeReport": ".engine",
    "load_engine": ".engine",
    "EngineConfig": ".config",
    "EngineKnobs": ".config",
    "ENGINE_KNOBS": ".config",
    "Database": ".database",
    "DatabaseError": ".database",
    "Regressor": ".database",
    "Codec": ".database",
    "register_codec": ".database",
    "write_model": ".database",
    "read_database": ".database",
    "write_database": ".database",
    "PoseModel": ".pose_models",
    "POSE_MODELS": ".pose_models",
    "register_pose_model": ".pose_models",
    "make_synthetic_database": ".synthetic",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
