"""`agentdress view`: the immersive display client - the three.js page of web/ (WebXR "Enter VR" on a headset),
served over HTTPS with an access token, fed over a WebSocket by an rclpy bridge (agentdress_ros.display).

The bridge discovers every `shape_msgs/Mesh` topic named `<prefix>/<garment>/mesh` in the ROS graph (the single
agent's `/agentdress_node/tshirt/mesh`, a crowd's `/agentdress_node/<agent>/tshirt/mesh`, any other node's) and the
matching `<prefix>/<garment>/points`; the agent is the prefix. Each node's `~/status` goes to the page's panel. A
shape slider publishes `std_msgs/Float32MultiArray` on the agent's body-shape topic: a crowd agent's
`/<agent>/body_shape` when the graph has it, else `/body_shape` (the single agent's default). A mesh with
`<prefix>/<garment>/skin` and `.../bones` topics (the body) is streamed as bone transforms instead of its points: the
page skins it on the GPU (three.js SkinnedMesh), exactly as the node did.

Security: the page, its files and the socket answer 403 without the random token printed in the URL at start; the
certificate is self-signed, made at first start (~/.config/agentdress/tls), so a browser asks once to accept it; a
certificate or key that does not load, or a key other users can read, stops the start with what to do (docs/viewer.md).
A headset on USB reaches the machine's localhost with `adb reverse tcp:8765 tcp:8765` (open the printed URL there).
"""
from __future__ import annotations

import argparse
import ipaddress
import json
import re
import sys
import threading

from ..viewer.state import DisplayScene
from ..viewer.server import MAX_CLIENTS, DisplayServer, NpmMissing, web_root
from ..viewer.tls import CertificateError, ensure_certificate, server_context

__all__ = ["RosBridge", "build_parser", "exposure_warning", "view_main"]

MESH_TOPIC = re.compile(r"^(/.+)/(\w+)/mesh$")


class RosBridge:
    """Fills a DisplayScene from the ROS graph (checked every second for new topics); publishes body shapes."""

    def __init__(self, scene: DisplayScene, node_filter: str | None = None):
        import rclpy
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        self.rclpy, self.scene = rclpy, scene
        self.filter = None if not node_filter else "/" + node_filter.strip("/")
        self.node = rclpy.create_node("agentdress_viewer")
        self.mesh_qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                                   durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.points_qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                                     reliability=ReliabilityPolicy.BEST_EFFORT)
        self.shape_qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
        self.subscribed: set[str] = set()
        self.point_subs: dict[str, object] = {}  # mesh topic -> its points subscription (until a skin shows up)
        self.skinned: set[str] = set()
        self.status_sources: set[str] = set()
        self.shape_publishers: dict = {}
        self._shape_lock = threading.Lock()  # publish_shape runs on the server's worker threads, one per client
        self.topics: frozenset = frozenset()  # the graph's topic names at the last discovery (for shape topics)
        self.discover()
        self.node.create_timer(1.0, self.discover)

    def discover(self):
        from sensor_msgs.msg import PointCloud2
        from shape_msgs.msg import Mesh
        from std_msgs.msg import String

        from .messages import mesh_to_arrays, serialized_cloud_to_vertices

        topics = dict(self.node.get_topic_names_and_types())
        self.topics = frozenset(topics)
        for topic, types in topics.items():
            match = MESH_TOPIC.match(topic)
            if not match or "shape_msgs/msg/Mesh" not in types:
                continue
            prefix, garment = match.groups()
            if self.filter and not (prefix == self.filter or prefix.startswith(self.filter + "/")):
                continue
            agent = prefix.lstrip("/")
            # the status of the node that publishes it: the prefix itself, or its parent for a crowd agent. Checked
            # every round: the graph may list a node's mesh topic a round before its status topic.
            for source in (prefix, prefix.rsplit("/", 1)[0]):
                status_topic = f"{source}/status"
                if source and status_topic in topics and source not in self.status_sources:
                    self.status_sources.add(source)
                    self.node.create_subscription(String, status_topic, lambda msg, s=source: self._on_status(s, msg),
                                                  10)
            if topic not in self.skinned and f"{prefix}/{garment}/skin" in topics \
                    and f"{prefix}/{garment}/bones" in topics:
                self._subscribe_skin(topic, prefix, agent, garment)
            if topic in self.subscribed:
                continue
            self.subscribed.add(topic)

            def on_mesh(msg, agent=agent, garment=garment):
                vertices, faces = mesh_to_arrays(msg)
                self.scene.set_mesh(agent, garment, vertices, faces)

            on_points = self._frame_reader(f"{prefix}/{garment}/points", serialized_cloud_to_vertices,
                                           lambda v, s, a=agent, g=garment: self.scene.set_vertices(a, g, v, s))
            self.node.create_subscription(Mesh, topic, on_mesh, self.mesh_qos)
            if topic not in self.skinned:
                self.point_subs[topic] = self.node.create_subscription(
                    PointCloud2, f"{prefix}/{garment}/points", on_points, self.points_qos, raw=True)

    def _subscribe_skin(self, topic: str, prefix: str, agent: str, garment: str):
        """Stream a skinned mesh as its binding and bone transforms; its points are no longer taken."""
        from geometry_msgs.msg import PoseArray
        from std_msgs.msg import Float32MultiArray

        from .messages import serialized_bones_to_transforms, skin_to_arrays

        def on_skin(msg):
            try:
                self.scene.set_skin(agent, garment, *skin_to_arrays(msg))
            except ValueError as error:
                self.node.get_logger().warning(f"{prefix}/{garment}/skin: {error}", throttle_duration_sec=5.0)

        on_bones = self._frame_reader(f"{prefix}/{garment}/bones", serialized_bones_to_transforms,
                                      lambda t, s: self.scene.set_bones(agent, garment, t, s))

        self.skinned.add(topic)
        points = self.point_subs.pop(topic, None)
        if points is not None:
            self.node.destroy_subscription(points)
        self.node.create_subscription(Float32MultiArray, f"{prefix}/{garment}/skin", on_skin, self.mesh_qos)
        self.node.create_subscription(PoseArray, f"{prefix}/{garment}/bones", on_bones, self.points_qos, raw=True)

    def _frame_reader(self, topic: str, parse, store):
        """A raw subscription's callback: `parse` (bytes -> (array, stamp s), ValueError on bad bytes) then
        `store(array, stamp)`; bad bytes get a warning at most every 5 s and change nothing."""
        def callback(data):
            try:
                value, stamp = parse(data)
            except ValueError as error:
                self.node.get_logger().warning(f"{topic}: {error}", throttle_duration_sec=5.0)
                return
            store(value, stamp)

        return callback

    def _on_status(self, source: str, msg):
        try:
            status = json.loads(msg.data)
        except ValueError:
            return
        if isinstance(status, dict):
            self.scene.set_status(source, status)

    def shape_topic(self, agent: str) -> str:
        """The body-shape input of an agent: `/<last name>/body_shape` if the graph has it (crowd), else
        `/body_shape`. From the graph of the last discovery (every second, on the ROS thread): no graph lookup per
        shape."""
        own = f"/{agent.rsplit('/', 1)[-1]}/body_shape"
        return own if "/" in agent and own in self.topics else "/body_shape"

    def publish_shape(self, agent: str, values):
        """Called from a worker thread of the display server (rclpy publishers are thread-safe)."""
        from std_msgs.msg import Float32MultiArray

        topic = self.shape_topic(agent)
        with self._shape_lock:
            publisher = self.shape_publishers.get(topic)
            if publisher is None:
                publisher = self.shape_publishers[topic] = self.node.create_publisher(Float32MultiArray, topic,
                                                                                      self.shape_qos)
        publisher.publish(Float32MultiArray(data=[float(v) for v in values]))

    def spin(self, ready=lambda: None):
        """Spins on rclpy's events executor: a crowd's clouds arrive by the thousand a second, and the default
        executor, which rebuilds its wait set over every subscription per wake-up, spent 4x the CPU on them.
        ready() is called once the executor is made: a Ctrl-C from then on (or while it is made) is a clean stop."""
        from rclpy.experimental import EventsExecutor

        from .spin import spin_until_shutdown

        def spin():  # its spin() neither ran this node's timer nor returned on shutdown (rclpy 7.1); spin_once does
            executor = EventsExecutor()
            executor.add_node(self.node)
            ready()
            while self.rclpy.ok():
                executor.spin_once(timeout_sec=0.1)

        spin_until_shutdown(spin)


def exposure_warning(host: str) -> str:
    """'' for a loopback host, else the warning that the stream is reachable beyond this machine."""
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name other than localhost: may resolve to anything
        loopback = False
    if loopback:
        return ""
    return (f"agentdress view: warning: serving on {host or '0.0.0.0'}, beyond this machine: anyone who can reach "
            "this address and has the printed URL (its token) can watch the stream and set the body shape")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agentdress view", description="immersive display client (three.js, WebXR)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to serve on (default: this machine only; 0.0.0.0 for a headset on the LAN)")
    parser.add_argument("--port", type=int, default=8765, help="HTTPS port (0: any free port; the URL is printed)")
    parser.add_argument("--node", default=None,
                        help="show only the meshes under this node's name (default: every agent in the graph)")
    parser.add_argument("--no-tls", action="store_true",
                        help="plain HTTP (WebXR then works only on localhost, e.g. through adb reverse)")
    parser.add_argument("--cert-dir", default=None, help="where the self-signed certificate is kept "
                                                         "(default ~/.config/agentdress/tls)")
    parser.add_argument("--web", default=None, help="client folder (default: web/ of this checkout)")
    parser.add_argument("--max-clients", type=int, default=MAX_CLIENTS,
                        help=f"WebSockets served at once (default {MAX_CLIENTS}); one more is closed with code 1013")
    return parser


def view_main(argv=None) -> int:
    """`agentdress view [--host 127.0.0.1] [--port 8765] [--node NAME] [--no-tls] [--ros-args ...]`: serves the
    client and prints `agentdress view: open https://HOST:PORT/TOKEN/`; runs until Ctrl-C. Returns the exit status."""
    import rclpy

    from ..body import PHENOTYPE_NAMES

    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    parser = build_parser()
    args = parser.parse_args(argv[: len(argv) - len(ros_args)])
    if args.max_clients < 1:
        parser.error("--max-clients must be 1 or more")
    try:
        web = web_root(args.web)
    except NpmMissing as error:
        print(f"agentdress view: error: {error}", file=sys.stderr)
        return 2
    certificate = None
    if not args.no_tls:
        try:
            cert, key, made = ensure_certificate(args.cert_dir)
            certificate = server_context(cert, key)
        except CertificateError as error:
            print(f"agentdress view: error: {error}", file=sys.stderr)
            return 2
        if made:
            print(f"agentdress view: made a self-signed certificate {cert} (the browser asks once to accept it)",
                  flush=True)
    scene = DisplayScene()
    rclpy.init(args=["agentdress_viewer", *ros_args])
    bridge = RosBridge(scene, args.node)
    server = DisplayServer(scene, web, args.host, args.port, certificate, on_shape=bridge.publish_shape,
                           phenotypes=PHENOTYPE_NAMES, max_clients=args.max_clients)
    try:
        server.start()
    except OSError as error:
        print(f"agentdress view: error: cannot serve on {args.host}:{args.port} ({error})", file=sys.stderr)
        bridge.node.destroy_node()
        rclpy.shutdown()
        return 2
    warning = exposure_warning(args.host)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    try:
        bridge.spin(ready=lambda: print(f"agentdress view: open {server.url()}", flush=True))
    finally:
        server.stop()
        bridge.node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(view_main())
