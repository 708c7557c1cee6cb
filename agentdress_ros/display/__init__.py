"""What the node publishes for display, without ROS (models.py): no skin through the cloth, garments layered, a
smooth mesh. The web viewer that shows it is agentdress_ros.viewer."""
