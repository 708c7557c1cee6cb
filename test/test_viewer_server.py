"""The display server under hostile input (issue 46), over real sockets on loopback, every loop bounded: file
errors, messages that escape validation, shape messages (unknown agents, clamping, floods, the thread they run on),
slow and surplus clients, bad certificate files, the key's mode, pipelined requests, security headers and the
WebSocket's Origin. Each test failed before its fix. No ROS here except the startup check of `agentdress view`."""
from __future__ import annotations

import asyncio
import base64
import hashlib
import http.client
import json
import logging
import os
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import websockets
from websockets.exceptions import ConnectionClosed, InvalidStatus

from agentdress_ros.viewer.state import DisplayScene
from agentdress_ros.viewer.server import DisplayServer
from agentdress_ros.viewer.tls import CertificateError, ensure_certificate, server_context

PHENOTYPES = ["gender", "age", "muscle", "weight", "height", "proportions"]
IMPORT_MAP = '\n{ "imports": { "three": "./three/build/three.module.js" } }\n'
AGENT = "agentdress_node"


def _web(folder: Path) -> Path:
    """A stand-in client folder: the server's answers do not depend on three.js being there."""
    (folder / "src").mkdir(parents=True)
    (folder / "index.html").write_text(f'<!doctype html><script type="importmap">{IMPORT_MAP}</script>')
    (folder / "src" / "main.js").write_text("export {};\n")
    return folder


def _scene(vertices: int = 3) -> DisplayScene:
    scene = DisplayScene()
    scene.set_mesh(AGENT, "tshirt", np.zeros((vertices, 3), np.float32), np.array([[0, 1, 2]]))
    return scene


def _frame_keys(frame: bytes) -> dict:
    """{mesh key: its entry} of a frame message (viewer.state.pack's layout)."""
    size = int.from_bytes(frame[:4], "little")
    return {m["key"]: m for m in json.loads(frame[4:4 + size])["meshes"]}


def test_a_body_bound_again_for_a_new_shape_keeps_its_last_pose():
    """A new shape rebinds the skinned body (a new rest): the client gets the new binding and, in the same update,
    the last bone transforms, so it never draws a frame of the body in its rest pose (under posed trousers, feet on
    the floor below a lifted knee). Bones for another skeleton are not carried over."""
    scene = DisplayScene()
    rest = np.zeros((3, 3), np.float32)
    indices, weights = np.array([[0], [1], [1]]), np.ones((3, 1), np.float32)
    scene.set_mesh(AGENT, "body", rest, np.array([[0, 1, 2]]))
    scene.set_skin(AGENT, "body", rest, indices, weights)
    pose = np.tile(np.hstack([np.eye(3), [[0.1], [0.2], [0.3]]]).astype(np.float32), (2, 1, 1))
    assert scene.set_bones(AGENT, "body", pose, stamp=5.0)
    seen = {}
    scene.updates(seen)
    scene.set_skin(AGENT, "body", rest + 0.01, indices, weights)  # the next shape
    meshes, _, frame, _ = scene.updates(seen)
    assert len(meshes) == 1 and frame is not None
    assert _frame_keys(frame)[f"{AGENT}/body"]["bones"] == 2
    scene.set_skin(AGENT, "body", rest, np.array([[0], [1], [4]]), weights)  # five bones: the old pose does not fit
    meshes, _, frame, _ = scene.updates(seen)
    assert len(meshes) == 1 and frame is None


def test_an_agents_meshes_reach_the_client_at_one_stamp():
    """The node publishes an agent's garments and body bones of one tick as separate topics: the client gets them
    at the newest stamp all of them have reached (trousers of one tick under the shirt of the one before showed
    through at the waist); a mesh that stopped publishing no longer holds the others back."""
    scene = DisplayScene()
    for garment in ("trousers", "tshirt"):
        scene.set_mesh(AGENT, garment, np.zeros((3, 3), np.float32), np.array([[0, 1, 2]]))

    def frame_at(stamp):
        return np.full((3, 3), stamp, np.float32)

    def sent(frame):
        size = int.from_bytes(frame[:4], "little")
        header = json.loads(frame[4:4 + size])
        payload = np.frombuffer(frame[4 + size:], dtype="<f4")
        return {m["key"].split("/")[1]: (m["stamp"], float(payload[m["offset"] // 4])) for m in header["meshes"]}

    seen = {}
    for garment in ("trousers", "tshirt"):
        scene.set_vertices(AGENT, garment, frame_at(1.0), stamp=1.0)
    scene.updates(seen)
    scene.set_vertices(AGENT, "trousers", frame_at(2.0), stamp=2.0)  # the shirt of tick 2 is still on its way
    assert scene.updates(seen)[2] is None  # nothing new at a stamp both have: the client keeps tick 1
    scene.set_vertices(AGENT, "tshirt", frame_at(2.0), stamp=2.0)
    assert sent(scene.updates(seen)[2]) == {"trousers": (2.0, 2.0), "tshirt": (2.0, 2.0)}
    for stamp in (3.0, 4.0, 5.0, 6.0):  # the shirt stops: past the kept frames the trousers go on alone
        scene.set_vertices(AGENT, "trousers", frame_at(stamp), stamp=stamp)
    assert sent(scene.updates(seen)[2]) == {"trousers": (6.0, 6.0)}


@pytest.fixture
def served(tmp_path):
    """A server with one agent; on_shape records (agent, values, thread name)."""
    shapes = []
    server = DisplayServer(_scene(), _web(tmp_path / "web"), "127.0.0.1", 0, phenotypes=PHENOTYPES,
                           on_shape=lambda agent, values: shapes.append((agent, values,
                                                                         threading.current_thread().name)))
    server.start()
    try:
        yield server, shapes
    finally:
        server.stop()


def _get(port: int, path: str, headers=None) -> tuple[int, dict, bytes]:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        connection.request("GET", path, headers=headers or {})
        response = connection.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        connection.close()


def _ws_url(server: DisplayServer) -> str:
    return f"ws://127.0.0.1:{server.port}/{server.token}/ws"


async def _replies(socket_, count: int, timeout: float = 10.0) -> list[dict]:
    """The next `count` JSON text messages (binary frames skipped)."""
    replies = []
    async with asyncio.timeout(timeout):
        while len(replies) < count:
            message = await socket_.recv()
            if isinstance(message, str):
                replies.append(json.loads(message))
    return replies


def _shape(agent=AGENT, values=(0.5,) * 6) -> str:
    return json.dumps({"type": "shape", "agent": agent, "values": list(values)})


def _wait(condition, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


# ---- 1: file errors ------------------------------------------------------------------------------------------------
def test_file_errors_answer_404_and_log_one_line_without_traceback(served, caplog):
    server, _ = served
    os.symlink("loop", server.web / "src" / "loop")  # a link to itself
    caplog.set_level(logging.INFO)
    token = f"/{server.token}"
    for path in (token + "/src/%00", token + "/src/a%00b.js", token + "/src/" + "a" * 300 + ".js",
                 token + "/src/loop", token + "/three/" + "b" * 300):
        status, _, body = _get(server.port, path)
        assert status == 404 and body == b"not found", (path[:60], status, body[:200])
    tracebacks = [r for r in caplog.records if r.exc_info or r.levelno >= logging.ERROR]
    assert not tracebacks, [r.getMessage() for r in tracebacks]
    lines = [r for r in caplog.records if r.name == "agentdress.display"]
    assert len(lines) == 4 and all("\n" not in r.getMessage() for r in lines), [r.getMessage() for r in lines]
    assert _get(server.port, token + "/src/main.js")[0] == 200  # and it goes on


# ---- 2 and 3: messages ---------------------------------------------------------------------------------------------
def test_deep_nesting_and_huge_integers_get_an_error_and_the_socket_goes_on(served):
    server, shapes = served

    async def probe():
        async with websockets.connect(_ws_url(server), open_timeout=10) as client:
            assert (await _replies(client, 1))[0]["type"] == "hello"
            answers = []
            for text in ("[" * 60_000, '{"a":' * 10_000 + "1" + "}" * 10_000,
                         _shape().replace("[0.5,", "[1" + "0" * 400 + ","),
                         _shape().replace("[0.5,", "[" + "9" * 5000 + ",")):
                await client.send(text)
                answers += await _replies(client, 1)
            await client.send(_shape(values=(0.25,) * 6))
            return answers

    answers = asyncio.run(probe())
    assert [a["type"] for a in answers] == ["error"] * 4, answers
    assert "nested too deep" in answers[0]["message"] and "nested too deep" in answers[1]["message"], answers
    assert "finite numbers" in answers[2]["message"] and "not JSON" in answers[3]["message"], answers
    assert _wait(lambda: len(shapes) == 1), shapes
    assert shapes[0][:2] == (AGENT, [0.25] * 6)


def test_shapes_only_for_known_agents_clamping_said_and_handed_over_off_the_event_loop(served):
    server, shapes = served

    async def probe():
        async with websockets.connect(_ws_url(server), open_timeout=10, max_size=2**20) as client:
            await _replies(client, 1)
            answers = []
            for agent in ("nobody", "../../evil", "x/" + AGENT, "n" * 60_000):
                await client.send(_shape(agent))
                answers += await _replies(client, 1)
            await client.send(_shape(values=(-5, 7, 0.5, 0.5, 0.5, 1)))
            answers += await _replies(client, 1)
            return answers

    answers = asyncio.run(probe())
    assert [a["type"] for a in answers] == ["error"] * 4 + ["warning"], answers
    assert all(f"no agent" in a["message"] and AGENT in a["message"] and len(a["message"]) < 400
               for a in answers[:4]), answers
    assert answers[4]["message"] == "shape values outside [0, 1] clamped: gender -5 -> 0, age 7 -> 1", answers
    assert _wait(lambda: len(shapes) == 1), shapes
    agent, values, thread = shapes[0]
    assert (agent, values) == (AGENT, [0.0, 1.0, 0.5, 0.5, 0.5, 1.0])
    assert thread != "agentdress-display", "on_shape ran on the server's event-loop thread"


def test_a_shape_flood_is_rate_limited_per_client_and_the_latest_value_wins(tmp_path):
    shapes = []
    interval = 0.5
    server = DisplayServer(_scene(), _web(tmp_path / "web"), "127.0.0.1", 0, phenotypes=PHENOTYPES,
                           on_shape=lambda agent, values: shapes.append((time.monotonic(), values)),
                           shape_rate_hz=1 / interval)
    server.start()
    last = [0.5, 0.5, 0.5, 499 / 499, 0.5, 0.5]

    async def flood():
        async with websockets.connect(_ws_url(server), open_timeout=10) as client:
            await _replies(client, 1)
            for i in range(500):
                await client.send(_shape(values=(0.5, 0.5, 0.5, i / 499, 0.5, 0.5)))
            for _ in range(100):  # until the last value went out (bounded: 10 s)
                if shapes and shapes[-1][1] == last:
                    break
                await asyncio.sleep(0.1)

    try:
        started = time.monotonic()
        asyncio.run(flood())
        elapsed = time.monotonic() - started
    finally:
        server.stop()
    assert shapes and shapes[-1][1] == last, shapes[-3:]
    # one publish per interval at most (the first at once): before the limit, 500 publishes
    assert len(shapes) <= 2 + elapsed / interval, (len(shapes), elapsed)
    gaps = np.diff([t for t, _ in shapes])
    assert len(gaps) == 0 or gaps.min() >= interval * 0.9, gaps


def test_the_bridge_picks_a_shape_topic_without_a_graph_lookup(monkeypatch, ros_domain):
    """The server hands shapes over on a worker thread; the ROS bridge then takes the agent's body-shape topic from
    its last discovery (every second, on the ROS thread) instead of asking the graph per shape."""
    rclpy = pytest.importorskip("rclpy", reason="rclpy (ros-jazzy-rclpy wheels) is not importable")
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float32MultiArray

    from agentdress_ros.ros.harness import ros_node, spin_until
    from agentdress_ros.ros.viewer import RosBridge

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    domain = ros_domain()
    received = []
    reliable = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
    with ros_node("shape_listener", domain) as (listener, executor):
        listener.create_subscription(Float32MultiArray, "/agent_001/body_shape",
                                     lambda msg: received.append(list(msg.data)), reliable)
        rclpy.init(domain_id=domain)
        try:
            bridge = RosBridge(DisplayScene())
            assert spin_until(executor, lambda: bridge.discover() or "/agent_001/body_shape" in bridge.topics, 20.0)
            lookups = []
            real = bridge.node.get_topic_names_and_types
            bridge.node.get_topic_names_and_types = lambda *a: lookups.append(1) or real(*a)
            bridge.publish_shape("agentdress_node/agent_001", [0.5] * 6)  # makes the publisher
            publisher = bridge.shape_publishers["/agent_001/body_shape"]
            assert spin_until(executor, lambda: publisher.get_subscription_count() == 1, 20.0)
            for _ in range(5):
                bridge.publish_shape("agentdress_node/agent_001", [0.25] * 6)
            assert spin_until(executor, lambda: received.count([0.25] * 6) == 5, 20.0), received
            bridge.node.destroy_node()
        finally:
            rclpy.shutdown()
    assert lookups == [], f"{len(lookups)} graph lookups for 6 shapes"


def test_a_status_topic_listed_after_its_mesh_topic_still_reaches_the_page(monkeypatch, ros_domain):
    """The graph may list a node's mesh topic a discovery round before its ~/status topic: the bridge subscribes to
    the status whenever it appears (before, a status missing in the mesh's first round was never subscribed)."""
    rclpy = pytest.importorskip("rclpy", reason="rclpy (ros-jazzy-rclpy wheels) is not importable")
    from shape_msgs.msg import Mesh
    from std_msgs.msg import String

    from agentdress_ros.ros.harness import ros_node, spin_until
    from agentdress_ros.ros.viewer import RosBridge

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    domain = ros_domain()
    with ros_node("agentdress_node", domain) as (node, executor):
        node.create_publisher(Mesh, "~/tshirt/mesh", 1)
        rclpy.init(domain_id=domain)
        try:
            scene = DisplayScene()
            bridge = RosBridge(scene)
            assert spin_until(executor, lambda: bridge.discover() or "/agentdress_node/tshirt/mesh" in bridge.topics,
                              20.0)
            assert bridge.status_sources == set()
            status = node.create_publisher(String, "~/status", 10)
            assert spin_until(executor, lambda: bridge.discover() or "/agentdress_node" in bridge.status_sources,
                              20.0), bridge.topics
            assert spin_until(executor, lambda: status.get_subscription_count() == 1, 20.0)
            status.publish(String(data=json.dumps({"frames": 7})))

            def delivered():
                rclpy.spin_once(bridge.node, timeout_sec=0.05)
                return scene.updates({})[3]

            assert spin_until(executor, delivered, 20.0)
            assert scene.updates({})[3] == [{"type": "status", "source": "/agentdress_node", "status": {"frames": 7}}]
            bridge.node.destroy_node()
        finally:
            rclpy.shutdown()


# ---- 4: slow and surplus clients -----------------------------------------------------------------------------------
def test_connections_past_the_limit_are_closed_with_1013(tmp_path):
    server = DisplayServer(_scene(), _web(tmp_path / "web"), "127.0.0.1", 0, max_clients=2)
    server.start()

    async def probe():
        async with websockets.connect(_ws_url(server), open_timeout=10) as first, \
                websockets.connect(_ws_url(server), open_timeout=10) as second:
            for client in (first, second):
                assert (await _replies(client, 1))[0]["type"] == "hello"
            async with websockets.connect(_ws_url(server), open_timeout=10) as third:
                with pytest.raises(ConnectionClosed) as closed:
                    await _replies(third, 1)
                refused = closed.value.rcvd
        assert _wait(lambda: server.clients == 0, 5.0)  # blocks this loop only: the server has its own thread
        async with websockets.connect(_ws_url(server), open_timeout=10) as again:  # room again once they left
            hello = (await _replies(again, 1))[0]
        return refused, hello

    try:
        refused, hello = asyncio.run(probe())
    finally:
        server.stop()
    assert refused.code == 1013 and "2 clients at most" in refused.reason, refused
    assert hello["type"] == "hello"


def _handshake(port: int, path: str, receive_buffer: int = 4096) -> socket.socket:
    """A WebSocket opened by hand on a socket with a small receive buffer, which then never reads."""
    raw = socket.socket()
    raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
    raw.settimeout(10)
    raw.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    raw.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
    response = b""
    while b"\r\n\r\n" not in response:
        response += raw.recv(1)
    assert response.startswith(b"HTTP/1.1 101"), response
    return raw


def test_a_client_that_stops_reading_is_dropped(tmp_path):
    """Frames of 1.2 MB (100,000 vertices) at the frame rate to a client that never reads: its frames stay unsent,
    and it is dropped once one stays unsent for send_timeout_s; the server goes on serving."""
    vertices = 100_000
    scene = _scene(vertices)
    server = DisplayServer(scene, _web(tmp_path / "web"), "127.0.0.1", 0, send_timeout_s=1.0)
    server.start()
    stop = threading.Event()

    def animate():  # new vertices every 10 ms for as long as the test runs
        rng = np.random.default_rng(0)
        frame = rng.normal(size=(vertices, 3)).astype(np.float32)
        while not stop.wait(0.01):
            scene.set_vertices(AGENT, "tshirt", frame)

    animator = threading.Thread(target=animate, daemon=True)
    animator.start()
    raw = _handshake(server.port, f"/{server.token}/ws")
    try:
        assert _wait(lambda: server.clients == 1, 5.0)
        dropped = _wait(lambda: server.clients == 0, 30.0)
        status = _get(server.port, f"/{server.token}/state.json")[0]
    finally:
        stop.set()
        animator.join(5)
        raw.close()
        server.stop()
    assert dropped, "a client that never reads was held for 30 s"
    assert status == 200


# ---- 5 and 6: certificate files and the key's mode -----------------------------------------------------------------
def _pair(folder: Path) -> tuple[Path, Path]:
    cert, key, made = ensure_certificate(folder)
    assert made
    return cert, key


@pytest.mark.parametrize("case", ["empty cert", "corrupt cert", "truncated cert", "empty key", "corrupt key",
                                  "truncated key", "mismatched key", "key is a folder", "cert is a folder"])
def test_bad_certificate_files_are_named_with_what_to_do(tmp_path, case):
    cert, key = _pair(tmp_path / "tls")
    target = cert if "cert" in case else key
    if case.startswith("empty"):
        target.write_bytes(b"")
    elif case.startswith("corrupt"):
        target.write_bytes(target.read_bytes().replace(b"A", b"@"))
    elif case.startswith("truncated"):
        target.write_bytes(target.read_bytes()[: len(target.read_bytes()) // 2])
    elif case == "mismatched key":
        key.write_bytes(_pair(tmp_path / "other")[1].read_bytes())
    else:
        target.unlink()
        target.mkdir()
    with pytest.raises(CertificateError) as error:
        server_context(*ensure_certificate(tmp_path / "tls")[:2])
    message = str(error.value)
    assert str(target) in message and "delete" in message, message
    assert ("is not the key of" in message) == (case == "mismatched key"), message
    assert ("not a file" in message) == ("folder" in case), message
    with pytest.raises(CertificateError):  # the server itself refuses the pair the same way
        DisplayServer(DisplayScene(), tmp_path, certificate=(cert, key))


def test_agentdress_view_stops_on_a_bad_certificate_with_the_file_named_and_no_traceback(tmp_path):
    pytest.importorskip("rclpy", reason="rclpy (ros-jazzy-rclpy wheels) is not importable")
    cert, key = _pair(tmp_path / "tls")
    cert.write_bytes(b"-----BEGIN CERTIFICATE-----\nnot a certificate\n-----END CERTIFICATE-----\n")
    web = _web(tmp_path / "web")
    (web / "node_modules" / "three" / "build").mkdir(parents=True)
    (web / "node_modules" / "three" / "build" / "three.module.js").write_text("")
    done = subprocess.run([sys.executable, "-m", "agentdress_ros.ros.viewer", "--port", "0", "--web", str(web),
                           "--cert-dir", str(tmp_path / "tls")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, (done.returncode, done.stderr[-3000:])
    assert str(cert) in done.stderr and "Traceback" not in done.stderr, done.stderr[-3000:]


def test_the_key_and_its_folder_are_owner_only_at_every_start(tmp_path):
    folder = tmp_path / "tls"
    cert, key = _pair(folder)
    assert stat.S_IMODE(key.stat().st_mode) == 0o600 and stat.S_IMODE(folder.stat().st_mode) == 0o700
    folder.chmod(0o755)  # an existing folder others can list: taken back to 0700 at the next start
    assert ensure_certificate(folder)[2] is False
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    key.chmod(0o644)  # a key others could read: refused, with what to do
    with pytest.raises(CertificateError) as error:
        ensure_certificate(folder)
    assert "readable by other users (mode 0644)" in str(error.value) and f"chmod 600 {key}" in str(error.value)
    with pytest.raises(CertificateError):
        server_context(cert, key)
    cert.unlink()  # a new pair written into the existing 0644 key file: the new key is owner-only
    assert ensure_certificate(folder)[2] is True
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    server_context(cert, key)


# ---- 7: pipelined requests -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("after", ["GET /{token}/ HTTP/1.1\r\nHost: x\r\n\r\n", "garbage after the request"])
def test_bytes_after_a_request_close_the_connection_without_a_traceback(served, caplog, after):
    server, _ = served
    caplog.set_level(logging.INFO)
    request = f"GET /{server.token}/ HTTP/1.1\r\nHost: x\r\n\r\n" + after.format(token=server.token)
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as raw:
        raw.sendall(request.encode())
        reply = b"".join(iter(lambda: raw.recv(65536), b""))  # until the server closes (10 s timeout)
    assert reply.startswith(b"HTTP/1.1 200") or reply == b"", reply[:200]
    assert reply.count(b"HTTP/1.1") <= 1, reply[:400]
    assert _wait(lambda: any(r.getMessage() == "connection closed" for r in caplog.records))  # its last log line
    problems = [r for r in caplog.records if r.exc_info or r.levelno >= logging.ERROR]
    assert not problems, [(r.name, r.getMessage()) for r in problems]
    assert _get(server.port, f"/{server.token}/")[0] == 200


# ---- 8: headers and the WebSocket's Origin -------------------------------------------------------------------------
def test_security_headers_and_a_policy_that_allows_exactly_the_page(served):
    server, _ = served
    status, headers, _ = _get(server.port, f"/{server.token}/")
    digest = base64.b64encode(hashlib.sha256(IMPORT_MAP.encode()).digest()).decode()
    assert status == 200
    assert headers["Content-Security-Policy"] == (
        f"default-src 'none'; script-src 'self' 'sha256-{digest}'; style-src 'self'; img-src 'self' data:; "
        "connect-src 'self'; worker-src 'self'; font-src data:; base-uri 'none'; form-action 'none'; "
        "frame-ancestors 'none'")
    assert headers["X-Frame-Options"] == "DENY" and headers["Referrer-Policy"] == "no-referrer"
    for path in ("/src/main.js", "/nothing", "/../"):  # every answer, refusals included
        headers = _get(server.port, f"/{server.token}{path}")[1]
        assert headers["X-Frame-Options"] == "DENY" and "Content-Security-Policy" in headers, path


def test_a_websocket_from_another_origin_is_refused(served):
    server, _ = served
    here = f"http://127.0.0.1:{server.port}"

    async def hello(origin):
        async with websockets.connect(_ws_url(server), open_timeout=10, origin=origin) as client:
            return (await _replies(client, 1))[0]["type"]

    for origin in ("http://evil.example", "null", f"http://127.0.0.1:{server.port + 1}"):
        with pytest.raises(InvalidStatus) as refused:
            asyncio.run(hello(origin))
        assert refused.value.response.status_code == 403, origin
    assert asyncio.run(hello(here)) == "hello"  # the page's own origin
    assert asyncio.run(hello(None)) == "hello"  # no Origin (not a browser): the token suffices
