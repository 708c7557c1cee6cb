"""`agentdress view`: a live web view of the dressed agent (an rclpy subscriber + a stdlib HTTP server).

Why this design: no dependency beyond rclpy and the standard library, nothing fetched at run time (no CDN, no npm),
works offline on any machine with a browser. The page is one self-contained HTML file with a hand-written WebGL
renderer (flat-shaded triangles, drag to orbit, wheel to zoom) and a 2D-canvas fallback (painter's algorithm) for
browsers without WebGL (e.g. headless Chromium with --disable-gpu). `viser` was the alternative: it installs
without torch, but pulls a websocket server, msgspec, trimesh extras and a ~10 MB prebuilt client for a feature we
use a fraction of.

HTTP endpoints (what the page polls; also handy for tests and scripts):
  /             the page
  /state.json   {"topology": generation, "seq": frames received, "meshes": {name: {"vertices", "faces",
                 "frames", "stamp"}}}
  /faces/<name> the faces (F, 3) of a mesh as little-endian uint32
  /frame?since=<seq>  long-poll (<= 1 s) for the next frame: uint32 header length, JSON header (names, vertex
                 counts, byte offsets, seq, topology), then each mesh's vertices (V, 3) as little-endian float32
A malformed request (a `since` that is not an integer, a broken request line) gets 400, an unknown path 404, a
method other than GET 405; the server goes on. It has no authentication: serving beyond this machine (--host other
than a loopback address) prints a warning.

The viewer discovers `<node>/<name>/mesh` topics (transient local: a late viewer still gets the topology) and the
matching `<node>/<name>/points` streams.
"""
from __future__ import annotations

import argparse
import ipaddress
import json
import re
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlparse

import numpy as np

__all__ = ["SceneState", "build_parser", "exposure_warning", "make_server", "view_main"]

COLORS = {"body": [0.85, 0.68, 0.56], "tshirt": [0.22, 0.45, 0.85], "longsleeve": [0.2, 0.65, 0.45],
          "trousers": [0.28, 0.28, 0.35]}


class SceneState:
    """What the viewer knows: topology per mesh and the latest vertices, guarded by one condition variable."""

    def __init__(self):
        self.cond = threading.Condition()
        self.faces: dict[str, np.ndarray] = {}  # name -> (F, 3) uint32
        self.vertices: dict[str, np.ndarray] = {}  # name -> (V, 3) float32
        self.frames: dict[str, int] = {}
        self.stamps: dict[str, float] = {}
        self.topology = 0
        self.seq = 0

    def set_mesh(self, name: str, vertices: np.ndarray, faces: np.ndarray):
        with self.cond:
            self.faces[name] = np.ascontiguousarray(faces, dtype="<u4")
            self.vertices[name] = np.ascontiguousarray(vertices, dtype="<f4")
            self.frames.setdefault(name, 0)
            self.topology += 1
            self.seq += 1
            self.cond.notify_all()

    def set_vertices(self, name: str, vertices: np.ndarray, stamp: float):
        with self.cond:
            faces = self.faces.get(name)
            # A cloud that does not fit the known topology (a garment rebuilt at another level of detail whose new
            # mesh has not arrived yet) is held back rather than drawn wrongly.
            if faces is None or (len(faces) and int(faces.max()) >= len(vertices)):
                return
            self.vertices[name] = np.ascontiguousarray(vertices, dtype="<f4")
            self.frames[name] = self.frames.get(name, 0) + 1
            self.stamps[name] = stamp
            self.seq += 1
            self.cond.notify_all()

    def state(self) -> dict:
        with self.cond:
            return {"topology": self.topology, "seq": self.seq,
                    "meshes": {n: {"vertices": len(self.vertices.get(n, ())), "faces": len(f),
                                   "frames": self.frames.get(n, 0), "stamp": self.stamps.get(n),
                                   "color": COLORS.get(n, [0.6, 0.6, 0.6])}
                               for n, f in sorted(self.faces.items())}}

    def frame(self, since: int, timeout: float = 1.0) -> bytes:
        with self.cond:
            self.cond.wait_for(lambda: self.seq > since, timeout=timeout)
            names = sorted(n for n in self.faces if n in self.vertices)
            header = {"seq": self.seq, "topology": self.topology, "meshes": []}
            blobs, offset = [], 0
            for n in names:
                blob = self.vertices[n].tobytes()
                header["meshes"].append({"name": n, "vertices": len(self.vertices[n]), "offset": offset})
                blobs.append(blob)
                offset += len(blob)
        text = json.dumps(header).encode()
        text += b" " * (-len(text) % 4)  # keep the float32 data 4-byte aligned for the browser's Float32Array
        return len(text).to_bytes(4, "little") + text + b"".join(blobs)


class RosBridge:
    """Subscribes to `<node>/<name>/mesh` and `<node>/<name>/points` as such topics appear (checked every second)."""

    def __init__(self, state: SceneState, node_name: str = "agentdress_node"):
        import rclpy
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        self.rclpy, self.state = rclpy, state
        self.prefix = "/" + node_name.strip("/")
        self.node = rclpy.create_node("agentdress_viewer")
        self.mesh_qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                                   durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.points_qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                                     reliability=ReliabilityPolicy.BEST_EFFORT)
        self.subscribed: set[str] = set()
        self.pattern = re.compile("^" + re.escape(self.prefix) + r"/(\w+)/mesh$")
        self.discover()
        self.node.create_timer(1.0, self.discover)

    def discover(self):
        from sensor_msgs.msg import PointCloud2
        from shape_msgs.msg import Mesh

        from .messages import cloud_to_vertices, mesh_to_arrays

        for topic, _types in self.node.get_topic_names_and_types():
            match = self.pattern.match(topic)
            if not match or match.group(1) in self.subscribed:
                continue
            name = match.group(1)
            self.subscribed.add(name)

            def on_mesh(msg, name=name):
                vertices, faces = mesh_to_arrays(msg)
                self.state.set_mesh(name, vertices, faces)

            def on_points(msg, name=name):
                stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                self.state.set_vertices(name, cloud_to_vertices(msg), stamp)

            self.node.create_subscription(Mesh, f"{self.prefix}/{name}/mesh", on_mesh, self.mesh_qos)
            self.node.create_subscription(PointCloud2, f"{self.prefix}/{name}/points", on_points, self.points_qos)

    def spin(self):
        from .spin import spin_until_shutdown

        spin_until_shutdown(lambda: self.rclpy.spin(self.node))


def _handler(state: SceneState):
    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args):  # quiet: one line per poll would flood the terminal
            pass

        def _send(self, body: bytes, content_type: str, status: int = 200):
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self):
            url = urlparse(self.path)
            try:
                if url.path in ("/", "/index.html"):
                    self._send(PAGE.encode(), "text/html; charset=utf-8")
                elif url.path == "/state.json":
                    self._send(json.dumps(state.state()).encode(), "application/json")
                elif url.path.startswith("/faces/"):
                    name = url.path[len("/faces/"):]
                    with state.cond:
                        faces = state.faces.get(name)
                    if faces is None:
                        self._send(b"unknown mesh", "text/plain", 404)
                    else:
                        self._send(faces.tobytes(), "application/octet-stream")
                elif url.path == "/frame":
                    text = parse_qs(url.query, keep_blank_values=True).get("since", ["-1"])[0]
                    try:
                        since = int(text)
                    except ValueError:
                        self._send(f"bad request: since={text[:40]!r} is not an integer".encode(), "text/plain", 400)
                        return
                    self._send(state.frame(since), "application/octet-stream")
                else:
                    self._send(b"not found", "text/plain", 404)
            except (BrokenPipeError, ConnectionResetError):
                pass
            except Exception as error:  # a bug answers 500 instead of dropping the connection; the server goes on
                self._send(f"internal error: {error!r}".encode(), "text/plain", 500)

        def _not_allowed(self):
            self.send_response(405)
            self.send_header("Allow", "GET")
            self.send_header("Content-Length", "0")
            self.end_headers()

        do_POST = do_PUT = do_DELETE = do_PATCH = do_HEAD = do_OPTIONS = _not_allowed

    return Handler


def make_server(state: SceneState, host: str = "127.0.0.1", port: int = 8765) -> ThreadingHTTPServer:
    server = ThreadingHTTPServer((host, port), _handler(state))
    server.daemon_threads = True
    return server


def exposure_warning(host: str) -> str:
    """'' for a loopback host, else the warning that anyone reaching the address sees the stream."""
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name other than localhost: may resolve to anything
        loopback = False
    if loopback:
        return ""
    return (f"agentdress view: warning: serving on {host or '0.0.0.0'}, beyond this machine; the viewer has no "
            "authentication: anyone who can reach this address sees the stream")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agentdress view", description="live web view of the dressed agent")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (default: this machine only)")
    parser.add_argument("--port", type=int, default=8765, help="HTTP port (0: any free port; the URL is printed)")
    parser.add_argument("--node", default="agentdress_node", help="name of the agentdress node to display")
    return parser


def view_main(argv=None) -> int:
    """`agentdress view [--host 127.0.0.1] [--port 8765] [--node agentdress_node] [--ros-args ...]`: serves the
    page and prints `agentdress view: open http://HOST:PORT/`; runs until Ctrl-C. Returns the exit status."""
    import rclpy

    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    args = build_parser().parse_args(argv[: len(argv) - len(ros_args)])
    state = SceneState()
    try:
        server = make_server(state, args.host, args.port)
    except OSError as error:
        print(f"agentdress view: error: cannot serve on {args.host}:{args.port} ({error})", file=sys.stderr)
        return 2
    warning = exposure_warning(args.host)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    rclpy.init(args=["agentdress_viewer", *ros_args])
    bridge = RosBridge(state, args.node)
    threading.Thread(target=server.serve_forever, name="agentdress-http", daemon=True).start()
    host, port = server.server_address[:2]
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
    print(f"agentdress view: open http://{shown}:{port}/", flush=True)
    try:
        bridge.spin()
    finally:
        server.shutdown()
        bridge.node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


PAGE = r"""<!doctype html>
<html><head><meta charset="utf-8"><title>agentdress view</title>
<style>
 html, body { margin: 0; height: 100%; background: #eef0f3; font: 13px sans-serif; overflow: hidden; }
 canvas { display: block; width: 100%; height: 100%; }
 #info { position: absolute; left: 8px; top: 6px; color: #333; background: rgba(255,255,255,.7); padding: 2px 6px; }
</style></head>
<body><canvas id="c"></canvas><div id="info">agentdress view: waiting for the node...</div>
<script>
"use strict";
const canvas = document.getElementById("c"), info = document.getElementById("info");
const meshes = {};            // name -> {faces: Uint32Array, vertices: Float32Array, color: [r,g,b], buffers}
let topology = -1, seq = -1, yaw = 0.35, pitch = 0.12, distance = 3.2, renderer = null, frames = 0;

function makeWebGL() {
  const gl = canvas.getContext("webgl", {antialias: true, preserveDrawingBuffer: true});
  if (!gl) return null;
  const vs = `attribute vec3 p; attribute vec3 n; uniform mat4 m; varying vec3 vn;
              void main() { vn = n; gl_Position = m * vec4(p, 1.0); }`;
  const fs = `precision mediump float; varying vec3 vn; uniform vec3 color;
              void main() { vec3 l = normalize(vec3(0.3, -0.8, 0.6)); vec3 nn = normalize(vn);
                float d = abs(dot(nn, l)); gl_FragColor = vec4(color * (0.35 + 0.65 * d), 1.0); }`;
  function shader(type, src) { const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s); return s; }
  const prog = gl.createProgram();
  gl.attachShader(prog, shader(gl.VERTEX_SHADER, vs)); gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) return null;
  gl.getExtension("OES_element_index_uint");
  const loc = {p: gl.getAttribLocation(prog, "p"), n: gl.getAttribLocation(prog, "n"),
               m: gl.getUniformLocation(prog, "m"), color: gl.getUniformLocation(prog, "color")};
  return {
    name: "WebGL",
    draw(matrix) {
      gl.viewport(0, 0, canvas.width, canvas.height);
      gl.clearColor(0.933, 0.941, 0.953, 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
      gl.enable(gl.DEPTH_TEST); gl.useProgram(prog);
      gl.uniformMatrix4fv(loc.m, false, matrix);
      for (const name in meshes) {
        const m = meshes[name];
        if (!m.vertices || !m.faces) continue;
        if (!m.gl) {
          m.gl = {p: gl.createBuffer(), n: gl.createBuffer(), i: gl.createBuffer()};
          gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, m.gl.i); gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, m.faces, gl.STATIC_DRAW);
        }
        gl.bindBuffer(gl.ARRAY_BUFFER, m.gl.p); gl.bufferData(gl.ARRAY_BUFFER, m.vertices, gl.DYNAMIC_DRAW);
        gl.enableVertexAttribArray(loc.p); gl.vertexAttribPointer(loc.p, 3, gl.FLOAT, false, 0, 0);
        gl.bindBuffer(gl.ARRAY_BUFFER, m.gl.n); gl.bufferData(gl.ARRAY_BUFFER, normals(m), gl.DYNAMIC_DRAW);
        gl.enableVertexAttribArray(loc.n); gl.vertexAttribPointer(loc.n, 3, gl.FLOAT, false, 0, 0);
        gl.uniform3fv(loc.color, m.color);
        gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, m.gl.i);
        gl.drawElements(gl.TRIANGLES, m.faces.length, gl.UNSIGNED_INT, 0);
      }
    },
    forget(m) { if (m.gl) { gl.deleteBuffer(m.gl.p); gl.deleteBuffer(m.gl.n); gl.deleteBuffer(m.gl.i); m.gl = null; } }
  };
}

function make2D() {  // painter's algorithm: sort triangles back to front, fill flat-shaded
  const ctx = canvas.getContext("2d");
  return {
    name: "2D canvas",
    draw(matrix) {
      ctx.fillStyle = "#eef0f3"; ctx.fillRect(0, 0, canvas.width, canvas.height);
      const tris = [];
      for (const name in meshes) {
        const m = meshes[name];
        if (!m.vertices || !m.faces) continue;
        const v = m.vertices, f = m.faces, nv = v.length / 3, sx = new Float32Array(nv), sy = new Float32Array(nv),
              sz = new Float32Array(nv);
        for (let i = 0; i < nv; i++) {
          const x = v[3*i], y = v[3*i+1], z = v[3*i+2];
          const w = matrix[3]*x + matrix[7]*y + matrix[11]*z + matrix[15];
          sx[i] = ((matrix[0]*x + matrix[4]*y + matrix[8]*z + matrix[12]) / w * 0.5 + 0.5) * canvas.width;
          sy[i] = (0.5 - (matrix[1]*x + matrix[5]*y + matrix[9]*z + matrix[13]) / w * 0.5) * canvas.height;
          sz[i] = (matrix[2]*x + matrix[6]*y + matrix[10]*z + matrix[14]) / w;
        }
        for (let t = 0; t < f.length; t += 3) {
          const a = f[t], b = f[t+1], c = f[t+2];
          const ux = v[3*b]-v[3*a], uy = v[3*b+1]-v[3*a+1], uz = v[3*b+2]-v[3*a+2];
          const wx = v[3*c]-v[3*a], wy = v[3*c+1]-v[3*a+1], wz = v[3*c+2]-v[3*a+2];
          let nx = uy*wz-uz*wy, ny = uz*wx-ux*wz, nz = ux*wy-uy*wx;
          const len = Math.hypot(nx, ny, nz) || 1;
          const d = Math.abs((0.3*nx - 0.8*ny + 0.6*nz) / len / 1.044);
          tris.push([sz[a] + sz[b] + sz[c], sx[a], sy[a], sx[b], sy[b], sx[c], sy[c], m.color, 0.35 + 0.65*d]);
        }
      }
      tris.sort((p, q) => q[0] - p[0]);
      for (const t of tris) {
        const s = t[8], c = t[7];
        ctx.fillStyle = `rgb(${255*c[0]*s|0},${255*c[1]*s|0},${255*c[2]*s|0})`;
        ctx.strokeStyle = ctx.fillStyle;
        ctx.beginPath(); ctx.moveTo(t[1], t[2]); ctx.lineTo(t[3], t[4]); ctx.lineTo(t[5], t[6]); ctx.closePath();
        ctx.fill(); ctx.stroke();
      }
    },
    forget(m) {}
  };
}

function normals(m) {
  const v = m.vertices, f = m.faces, n = new Float32Array(v.length);
  for (let t = 0; t < f.length; t += 3) {
    const a = 3*f[t], b = 3*f[t+1], c = 3*f[t+2];
    const ux = v[b]-v[a], uy = v[b+1]-v[a+1], uz = v[b+2]-v[a+2], wx = v[c]-v[a], wy = v[c+1]-v[a+1], wz = v[c+2]-v[a+2];
    const nx = uy*wz-uz*wy, ny = uz*wx-ux*wz, nz = ux*wy-uy*wx;
    n[a] += nx; n[a+1] += ny; n[a+2] += nz; n[b] += nx; n[b+1] += ny; n[b+2] += nz; n[c] += nx; n[c+1] += ny; n[c+2] += nz;
  }
  return n;
}

function viewMatrix() {  // perspective * look-at around the agent's centre (Z up, the agent faces -Y)
  let cx = 0, cy = 0, cz = 0.9, count = 0;
  for (const name in meshes) {
    const v = meshes[name].vertices; if (!v) continue;
    for (let i = 0; i < v.length; i += 30) { cx += v[i]; cy += v[i+1]; count++; }
  }
  if (count) { cx /= count; cy /= count; }
  const ex = cx + distance * Math.cos(pitch) * Math.sin(yaw), ey = cy - distance * Math.cos(pitch) * Math.cos(yaw),
        ez = cz + distance * Math.sin(pitch);
  let fx = cx - ex, fy = cy - ey, fz = cz - ez; const fl = Math.hypot(fx, fy, fz); fx /= fl; fy /= fl; fz /= fl;
  let sx = fy * 1 - fz * 0, sy = fz * 0 - fx * 1, sz = 0; const sl = Math.hypot(sx, sy, sz); sx /= sl; sy /= sl;
  const ux = sy * fz - sz * fy, uy = sz * fx - sx * fz, uz = sx * fy - sy * fx;
  const aspect = canvas.width / canvas.height, f = 1 / Math.tan(0.5 * 0.75), near = 0.05, far = 50;
  const view = [sx, ux, -fx, 0, sy, uy, -fy, 0, sz, uz, -fz, 0,
                -(sx*ex + sy*ey + sz*ez), -(ux*ex + uy*ey + uz*ez), (fx*ex + fy*ey + fz*ez), 1];
  const proj = [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, 2 * far * near / (near - far), 0];
  const out = new Float32Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let s = 0; for (let k = 0; k < 4; k++) s += proj[k*4 + r] * view[c*4 + k]; out[c*4 + r] = s;
  }
  return out;
}

function resize() {
  const w = canvas.clientWidth || 800, h = canvas.clientHeight || 600;
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
}

function draw() { resize(); if (renderer) renderer.draw(viewMatrix()); }

async function loadTopology() {
  const state = await (await fetch("/state.json")).json();
  for (const name in meshes) if (!(name in state.meshes)) { renderer.forget(meshes[name]); delete meshes[name]; }
  for (const name in state.meshes) {
    const faces = new Uint32Array(await (await fetch("/faces/" + name)).arrayBuffer());
    if (meshes[name]) renderer.forget(meshes[name]);
    meshes[name] = {faces, vertices: null, color: state.meshes[name].color};
  }
  topology = state.topology;
}

async function poll() {
  try {
    const buf = await (await fetch("/frame?since=" + seq)).arrayBuffer();
    const length = new DataView(buf).getUint32(0, true);
    const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, length)));
    if (header.topology !== topology) await loadTopology();
    for (const m of header.meshes) {
      if (meshes[m.name] && m.vertices > 0) meshes[m.name].vertices = new Float32Array(buf, 4 + length + m.offset, 3 * m.vertices);
    }
    if (header.seq !== seq) { seq = header.seq; frames++; draw(); }
    info.textContent = `agentdress view (${renderer.name}): ${Object.keys(meshes).join(", ") || "no meshes yet"}, frame ${frames}`;
    setTimeout(poll, 0);
  } catch (error) {
    info.textContent = "agentdress view: viewer not reachable, retrying... (" + error + ")";
    setTimeout(poll, 1000);
  }
}

let dragging = null;
canvas.addEventListener("mousedown", e => { dragging = [e.clientX, e.clientY]; });
window.addEventListener("mouseup", () => { dragging = null; });
window.addEventListener("mousemove", e => {
  if (!dragging) return;
  yaw += 0.01 * (e.clientX - dragging[0]); pitch = Math.max(-1.4, Math.min(1.4, pitch + 0.01 * (e.clientY - dragging[1])));
  dragging = [e.clientX, e.clientY]; draw();
});
canvas.addEventListener("wheel", e => { distance = Math.max(0.5, Math.min(20, distance * Math.exp(0.001 * e.deltaY))); draw(); e.preventDefault(); });
window.addEventListener("resize", draw);
resize();
renderer = (new URLSearchParams(location.search).get("renderer") === "2d" ? null : makeWebGL()) || make2D();
poll();
</script></body></html>
"""

if __name__ == "__main__":
    sys.exit(view_main())
