"""ROS 2 side: the agentdress_node (node.py, wiring only), its ROS-free parts (garment_models, inputs, params,
runtime), message packing (messages), the demo JointState player (demo), the web viewer (viewer), `make run`
(run_all) and the process harness used by tests and benchmarks (harness). Nothing here is imported by engine/."""
