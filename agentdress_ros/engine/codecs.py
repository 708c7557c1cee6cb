"""The modules that store an optional model in the database, each registering its Codec beside the model's code
(engine.database.register_codec). The database imports them, in this order, before it reads or writes a file, and
reads the groups in registration order: a group after those it needs (the recurrent correction after the regressor).
A new stored model adds its module here; database.py stays as it is."""

CODEC_MODULES = (
    "agentdress_ros.engine.pose_models",  # regressor, recurrent, kdsm_model
    "agentdress_ros.engine.santesteban",  # santesteban
    "agentdress_ros.engine.engine",  # shape_residual
)
