"""A crowd of dressed agents, without ROS: agents (pose input, shape, per-agent engine state over shared garment
data), levels of detail by distance with hysteresis and cross-fades (lod, garments), field-of-view culling, idle
skip, and the frame-budget scheduler (scheduler). `ros/` maps topics and parameters onto it; it never imports
rclpy."""
from .garments import AgentGarment, GarmentLibrary, GarmentSpec
from .lod import DEFAULT_TIERS, LodPolicy, Tier, Viewer, parse_tier, parse_tiers
from .pose import InputRejected, PoseInput
from .scene import Agent, AgentSpec, Scene, SceneConfig, TickReport
from .scheduler import Candidate, Decision, schedule

__all__ = ["DEFAULT_TIERS", "Agent", "AgentGarment", "AgentSpec", "Candidate", "Decision", "GarmentLibrary",
           "GarmentSpec", "InputRejected", "LodPolicy", "PoseInput", "Scene", "SceneConfig", "Tier", "TickReport",
           "Viewer", "parse_tier", "parse_tiers", "schedule"]
