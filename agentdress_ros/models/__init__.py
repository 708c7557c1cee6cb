"""The garment and body models the node and the scene run (garment_models.py): one small protocol over the engine,
linear blend skinning and the visible body, without ROS."""
