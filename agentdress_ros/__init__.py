"""agentdress_ros: real-time data-driven clothing for virtual humans (AgentDress) as a ROS 2 node."""
__version__ = "0.1.0"
