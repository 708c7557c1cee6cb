"""`agentdress bench look`: what the viewer's eye receives, frame by frame, on the real page (JSON on stdout).

The node (shipped databases, the node defaults, the body published: what `make run` starts) and the viewer run as
processes on a private ROS domain; this process publishes each pose (JointState, and the body shape) and waits until
the viewer and then the page hold that frame for every mesh. The shipped page (web/, three.js) in headless Chromium
with software WebGL (SwiftShader) loads web/src/look.js (?look=1), which draws the page's own meshes off screen at
512x512, fixed near and far planes, flat ID colours (background, body, each garment; no lighting, no antialiasing),
from views around the agent (VIEWS: four around at chest height, one from above, one at knee height), plus a
reference pass of the same frame with the body drawn whole. Per frame and view, counted in pixels:
- hole: background in the shown pass where the reference pass has the agent;
- skin-through: visible body pixels whose surface point (unprojected from the shown pass' depth) lies inside a
  garment's shell with its openings capped (that frame's drawn garment, never the body mask), unless the sight line
  to it passes one of the caps: skin seen through an opening (the neck down the collar, the ankle up the hem) is
  what cloth shows, skin seen where the cloth is closed is not;
- garment-through-garment: pixels of a lower layer's garment (display.models.TEMPLATE_LAYERS) whose surface point
  lies inside a higher layer's capped shell, with the same exception;
each as a share of the agent's silhouette (the reference pass' non-background pixels); and per frame and garment
the edge roughness of each open boundary as drawn: distance of its vertices from the boundary smoothed by a
Gaussian of SIGMA along its arc length (mm; a circle of radius R reads about SIGMA^2 / 2R from the smoothing's own
shrink: 3 mm on a 6 cm cuff), and the turning angle between boundary edges (degrees).
Reported: mean, p99 and max over frames and views (edges: over frames); the worst frames of each kind go to a
contact sheet PNG.
"""
from __future__ import annotations

import argparse
import base64
import heapq
import json
import shutil
import signal
import sys
import time
from pathlib import Path

import numba
import numpy as np

from ..garment.coverage import boundary_loops, ray_triangle

ROOT = Path(__file__).resolve().parents[2]
SIZE = 512
SIGMA = 0.02  # metres of arc length: the edge-smoothing Gaussian
#: views around the agent (three.js: azimuth about the vertical, degrees; elevation looking down, degrees; or a
#: camera height above the feet, metres, looking at the agent's centre)
VIEWS = ({"azimuth": 0, "elevation": 10}, {"azimuth": 90, "elevation": 10}, {"azimuth": 180, "elevation": 10},
         {"azimuth": 270, "elevation": 10}, {"azimuth": 45, "elevation": 60}, {"azimuth": 225, "height": 0.45})
KINDS = ("hole", "skin_through", "garment_through")
WORST = 12
#: the ID colours of the contact sheet (class 0 background, 1 body, then the garments) and of the counted pixels
SHEET_COLORS = np.array([[32, 36, 42], [217, 168, 140], [51, 107, 217], [77, 77, 97], [51, 166, 115],
                         [150, 150, 150]], dtype=np.uint8)
MARK = np.array([255, 0, 255], dtype=np.uint8)


# ---- geometry (pure array functions) -------------------------------------------------------------------------------
def capped(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The shell of a garment with its openings capped: vertices (V, 3), faces (G, 3) -> (V + L, 3), (G + C, 3),
    each open boundary closed by a fan from its centroid."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    points, fans = [vertices], [faces]
    for loop in boundary_loops(faces):
        centre = len(vertices) + len(points) - 1
        points.append(vertices[loop].mean(axis=0, keepdims=True))
        fans.append(np.stack([np.roll(loop, -1), loop, np.full(len(loop), centre)], axis=1))
    return np.concatenate(points), np.concatenate(fans)


@numba.njit(cache=True, nogil=True)
def _crossings(points, vertices, faces, low, cell, cols, rows, starts, members):
    """(P,) how many triangles faces (G, 3) over vertices (V, 3) the vertical ray up from each point (P, 3)
    crosses; the triangles of grid cell c (x, y cells of `cell` metres from `low`, row-major, cols x rows) are
    members[starts[c]:starts[c + 1]]."""
    count = np.zeros(points.shape[0], dtype=np.int64)
    for p in range(points.shape[0]):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        i, j = int(np.floor((px - low[0]) / cell)), int(np.floor((py - low[1]) / cell))
        if i < 0 or j < 0 or i >= cols or j >= rows:
            continue
        c = j * cols + i
        for k in range(starts[c], starts[c + 1]):
            t = members[k]
            a, b, d = faces[t, 0], faces[t, 1], faces[t, 2]
            x0, y0, x1, y1 = vertices[a, 0], vertices[a, 1], vertices[b, 0], vertices[b, 1]
            x2, y2 = vertices[d, 0], vertices[d, 1]
            det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
            if det == 0.0:
                continue
            l0 = ((y1 - y2) * (px - x2) + (x2 - x1) * (py - y2)) / det
            l1 = ((y2 - y0) * (px - x2) + (x0 - x2) * (py - y2)) / det
            l2 = 1.0 - l0 - l1
            if l0 >= 0.0 and l1 >= 0.0 and l2 >= 0.0 and \
                    l0 * vertices[a, 2] + l1 * vertices[b, 2] + l2 * vertices[d, 2] > pz:
                count[p] += 1
    return count


@numba.njit(cache=True, nogil=True)
def _segments_cross(starts, ends, vertices, faces):
    """(P,) bool: whether the segment from starts[p] to ends[p] (P, 3) crosses any triangle of faces (C, 3) over
    vertices (V, 3)."""
    out = np.zeros(starts.shape[0], dtype=np.bool_)
    for p in range(starts.shape[0]):
        ox, oy, oz = starts[p, 0], starts[p, 1], starts[p, 2]
        dx, dy, dz = ends[p, 0] - ox, ends[p, 1] - oy, ends[p, 2] - oz
        for t in range(faces.shape[0]):
            along, _, _ = ray_triangle(ox, oy, oz, dx, dy, dz, vertices, faces[t, 0], faces[t, 1], faces[t, 2])
            if 0.0 <= along <= 1.0:
                out[p] = True
                break
    return out


class Shell:
    """A garment vertices (V, 3), faces (G, 3) with its openings capped, indexed for inside tests: `inside(points)`
    (P,) bool - odd crossings of a vertical ray with the closed shell (points nudged 1e-7 m off exact edge hits);
    `through_opening(eyes, points)` (P,) bool - whether the sight line from each eye to its point passes a cap."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, cell: float = 0.02):
        self.vertices, self.faces = capped(vertices, faces)
        self.caps = self.faces[len(faces):]
        self.cell = cell
        self.low = self.vertices[:, :2].min(axis=0) - cell
        self.cols, self.rows = (np.ceil((self.vertices[:, :2].max(axis=0) + cell - self.low) / cell)).astype(int)
        corners = self.vertices[self.faces][:, :, :2]
        first = np.floor((corners.min(axis=1) - self.low) / cell).astype(np.int64)
        span = np.floor((corners.max(axis=1) - self.low) / cell).astype(np.int64) - first + 1
        per = span[:, 0] * span[:, 1]  # each triangle in every cell its x, y box touches
        triangle = np.repeat(np.arange(len(self.faces)), per)
        local = np.arange(per.sum()) - np.repeat(np.cumsum(per) - per, per)
        cells = (first[triangle, 1] + local // span[triangle, 0]) * self.cols + first[triangle, 0] \
            + local % span[triangle, 0]
        order = np.argsort(cells, kind="stable")
        self.starts = np.searchsorted(cells[order], np.arange(self.rows * self.cols + 1)).astype(np.int64)
        self.members = triangle[order].astype(np.int64)

    def inside(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3) + np.array([1.3e-7, 0.7e-7, 0.0])
        crossings = _crossings(points, self.vertices, self.faces, self.low, self.cell, int(self.cols),
                               int(self.rows), self.starts, self.members)
        return crossings % 2 == 1

    def through_opening(self, eyes: np.ndarray, points: np.ndarray) -> np.ndarray:
        eyes = np.asarray(eyes, dtype=np.float64).reshape(-1, 3)
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not len(self.caps):
            return np.zeros(len(points), dtype=bool)
        return _segments_cross(eyes, points, self.vertices, self.caps)


def edge_roughness(vertices: np.ndarray, loop: np.ndarray, sigma: float = SIGMA) -> tuple[np.ndarray, np.ndarray]:
    """One closed boundary loop (L,) of vertices (V, 3): (distance (L,) in mm of each vertex from the loop smoothed
    by a Gaussian of `sigma` metres along its arc length, turning angle (L,) in degrees between its edges). The
    smoothing is shrink-compensated (2 G*x - G*G*x): a plain Gaussian pulls a circle of radius R in by about
    sigma^2 / 2R (3 mm on a 6 cm cuff), which would read as roughness on the smoothest hem."""
    points = np.asarray(vertices, dtype=np.float64)[loop]
    edges = np.roll(points, -1, axis=0) - points
    lengths = np.linalg.norm(edges, axis=1)
    total = lengths.sum()
    s = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    gap = np.abs(s[:, None] - s[None, :])
    gap = np.minimum(gap, total - gap)  # along the closed loop
    weights = np.exp(-0.5 * (gap / sigma) ** 2) * (lengths + np.roll(lengths, 1))[None, :] / 2
    weights /= weights.sum(axis=1, keepdims=True)
    once = weights @ points
    smooth = 2 * once - weights @ once  # twice minus twice smoothed: the smoothing's own shrink cancels
    before = np.roll(edges, 1, axis=0)
    cosine = np.einsum("ij,ij->i", before, edges) / np.maximum(np.roll(lengths, 1) * lengths, 1e-18)
    return 1e3 * np.linalg.norm(points - smooth, axis=1), np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def find_chromium() -> str:
    """The system Chromium's path; RuntimeError saying how to install it when there is none."""
    found = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)
    if found is None:
        raise RuntimeError("no chromium / chromium-browser / google-chrome on PATH (Debian: apt-get install -y chromium)")
    return found


def decode_depth(rgba: np.ndarray) -> np.ndarray:
    """three.js' RGBA depth packing (packDepthToRGBA) of bytes (..., 4) -> window depth (...) in [0, 1]."""
    factors = np.array([255 / 256, 255 / 256 / 256, 255 / 256 / 65536, 1 / 16777216]) / 255.0
    return np.asarray(rgba, dtype=np.float64) @ factors


def unproject(rows: np.ndarray, cols: np.ndarray, depth: np.ndarray, matrix: np.ndarray, size: int) -> np.ndarray:
    """(P, 3) the node-frame points of pixels (rows counted bottom up, cols) at window depths (P,) through the
    page's window-to-node matrix (4, 4)."""
    ndc = np.stack([(cols + 0.5) / size * 2 - 1, (rows + 0.5) / size * 2 - 1, 2 * depth - 1, np.ones(len(rows))], 1)
    world = ndc @ matrix.T
    return world[:, :3] / world[:, 3:]


def view_counts(shown: np.ndarray, reference: np.ndarray, depth: np.ndarray, matrix: np.ndarray, classes: list,
                garments: dict, layers: dict) -> dict:
    """The pixel counts of one view: shown, reference (H, W) class maps (0 background, 1 body, 2.. the garments of
    `classes` [body key, garment keys...]), depth (H, W) the shown pass' window depth, matrix (4, 4) window to node
    frame, garments {key: (vertices (V, 3), faces (G, 3))} as drawn, layers {key: layer}. Returns {silhouette, hole,
    skin_through, garment_through, fill (the silhouette's share of the image height)} and the masks (H, W) bool of
    the three kinds under "masks"."""
    size = shown.shape[0]
    silhouette = reference != 0
    masks = {"hole": (shown == 0) & silhouette,
             "skin_through": np.zeros_like(silhouette), "garment_through": np.zeros_like(silhouette)}
    shells = {key: garments[key] if isinstance(garments[key], Shell) else Shell(*garments[key])
              for key in classes[1:]}

    def inside_any(cls: int, over) -> np.ndarray:
        rows, cols = np.nonzero(shown == cls)
        mask = np.zeros_like(silhouette)
        if len(rows) == 0:
            return mask
        points = unproject(rows, cols, depth[rows, cols], matrix, size)
        eyes = unproject(rows, cols, np.zeros(len(rows)), matrix, size)  # the same pixel on the near plane
        hit = np.zeros(len(rows), dtype=bool)
        for key in over:
            inside = shells[key].inside(points)
            if inside.any():  # seen through one of the garment's openings (into a collar, up a hem): not through cloth
                inside[inside] = ~shells[key].through_opening(eyes[inside], points[inside])
            hit |= inside
        mask[rows[hit], cols[hit]] = True
        return mask

    masks["skin_through"] = inside_any(1, list(shells))
    for k, key in enumerate(classes[1:]):
        outer = [o for o in shells if layers.get(o, 0) > layers.get(key, 0)]
        if outer:
            masks["garment_through"] |= inside_any(k + 2, outer)
    filled = np.nonzero(silhouette.any(axis=1))[0]
    return {"silhouette": int(silhouette.sum()), **{kind: int(masks[kind].sum()) for kind in KINDS},
            "fill": float((filled.max() - filled.min() + 1) / size) if len(filled) else 0.0, "masks": masks}


def summary(values) -> dict:
    values = np.asarray(values, dtype=np.float64)
    if len(values) == 0:
        return {"mean": None, "p99": None, "max": None}
    return {"mean": float(values.mean()), "p99": float(np.percentile(values, 99)), "max": float(values.max())}


# ---- the page ------------------------------------------------------------------------------------------------------
def _classes(text: str) -> np.ndarray:
    return np.frombuffer(base64.b64decode(text), dtype=np.uint8).reshape(SIZE, SIZE)


def decode_capture(captured: dict) -> list[dict]:
    """The page's capture -> per view {shown, reference (H, W) uint8 classes, depth (H, W), matrix (4, 4)} (rows
    bottom up)."""
    out = []
    for v in captured["views"]:
        rgba = np.frombuffer(base64.b64decode(v["depth"]), dtype=np.uint8).reshape(SIZE, SIZE, 4)
        out.append({"view": v["view"], "shown": _classes(v["shown"]), "reference": _classes(v["reference"]),
                    "depth": decode_depth(rgba), "matrix": np.array(v["unproject"], dtype=np.float64).reshape(4, 4).T})
    return out


def drawn_garments(captured: dict) -> dict:
    return {key: (np.asarray(g["positions"], dtype=np.float64).reshape(-1, 3),
                  np.asarray(g["faces"], dtype=np.int64).reshape(-1, 3)) for key, g in captured["garments"].items()}


class LookSession:
    """Node + viewer processes on a private ROS domain, this process' pose and shape publishers, and the page
    (?look=1) in headless Chromium; `show(rotvecs, root, shape)` brings one frame to the page, `capture(views)` draws
    it."""

    BROWSER_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox", "--disable-gpu-sandbox",
                    "--disable-background-networking", "--disable-component-update", "--disable-sync",
                    "--no-first-run", "--disable-quic"]

    def __init__(self, workdir: Path, data: Path = ROOT / "data", chromium: str | None = None, node_params=()):
        self.workdir, self.data, self.node_params = Path(workdir), Path(data), list(node_params)
        self.chromium = chromium
        self.shape = None

    def __enter__(self):
        import os
        import ssl

        import rclpy
        from playwright.sync_api import TimeoutError as PageTimeout
        from playwright.sync_api import sync_playwright
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float32MultiArray

        from ..ros.harness import ChildProcess, random_domain, ros_env
        from ..ros.run_all import GARMENTS, node_command

        self.chromium = self.chromium or find_chromium()
        self.workdir.mkdir(parents=True, exist_ok=True)
        domain = random_domain()
        env = ros_env(domain, str(self.workdir / "ros_log"))
        databases = {g: self.data / f"{g}_default.h5" for g in GARMENTS if (self.data / f"{g}_default.h5").is_file()}
        self.children = {
            "node": ChildProcess(node_command(ROOT / "config" / "agentdress.yaml", databases, self.node_params), env,
                                 self.workdir / "node.log"),
            "viewer": ChildProcess([sys.executable, "-m", "agentdress_ros.ros.viewer", "--port", "0", "--cert-dir",
                                    str(self.workdir / "tls")], env, self.workdir / "viewer.log"),
        }
        self.insecure = ssl.create_default_context()
        self.insecure.check_hostname, self.insecure.verify_mode = False, ssl.CERT_NONE
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("agentdress_look", context=self.context)
        reliable = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
        self.poses = self.node.create_publisher(JointState, "joint_states", reliable)
        self.shapes = self.node.create_publisher(Float32MultiArray, "body_shape", reliable)
        self.JointState, self.Float32MultiArray, self.PageTimeout = JointState, Float32MultiArray, PageTimeout
        self.playwright = sync_playwright().start()
        self.browser = self.playwright.chromium.launch(executable_path=self.chromium, headless=True,
                                                       args=self.BROWSER_ARGS)
        try:
            self.url = self._viewer_url()
            self.page = self.browser.new_page(ignore_https_errors=True, viewport={"width": 640, "height": 480})
            self.errors = []
            self.page.on("pageerror", lambda error: self.errors.append(str(error)))
            self.page.set_default_timeout(300_000)  # a loaded machine draws and loads slowly in software
            self.page.goto(self.url + "?look=1")
            self.page.wait_for_function("() => window.agentdressLook !== undefined", timeout=120_000)
            self.page.evaluate("() => { for (const p of document.querySelectorAll('#panel, .lil-gui')) p.style.display = 'none'; }")
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc):
        for close in (lambda: self.browser.close(), lambda: self.playwright.stop(), lambda: self.node.destroy_node(),
                      lambda: __import__("rclpy").shutdown(context=self.context)):
            try:
                close()
            except Exception:
                pass
        self.codes = {name: child.stop(grace=30.0) for name, child in self.children.items()}
        return False

    def _viewer_url(self, timeout: float = 120.0) -> str:
        import re

        viewer = self.children["viewer"]
        if not viewer.wait_for_output("open https://", timeout):
            raise RuntimeError(f"the viewer did not start: {viewer.output()}")
        return re.search(r"open (https://\S+)", viewer.output()).group(1)

    def state(self) -> dict:
        import urllib.request

        with urllib.request.urlopen(self.url + "state.json", timeout=10, context=self.insecure) as response:
            return json.loads(response.read())

    def _publish(self, rotvecs, root) -> float:
        from ..motion.joint_names import JOINT_NAMES

        msg = self.JointState()
        stamp = self.node.get_clock().now()
        msg.header.stamp = stamp.to_msg()
        msg.header.frame_id = "agent"
        msg.name = list(JOINT_NAMES)
        msg.position = np.concatenate([np.asarray(rotvecs).reshape(-1), np.asarray(root).reshape(3)]).tolist()
        self.poses.publish(msg)
        return stamp.nanoseconds * 1e-9

    def show(self, rotvecs, root, shape, timeout: float = 180.0):
        """Publish this pose (and shape) until the viewer and then the page hold its frame for every mesh."""
        if shape is not None and (self.shape is None or not np.allclose(shape, self.shape)):
            self.shape = np.asarray(shape, dtype=np.float64)
            rebuilt = f"""() => Object.values(agentdress.status()).some((s) => s.shape &&
                s.shape.every((b, i) => Math.abs(b - {json.dumps(self.shape.tolist())}[i]) < 1e-4))"""
            deadline = time.monotonic() + timeout
            while True:  # sent again until the node has rebuilt for it: the first may precede the node's subscription
                self.shapes.publish(self.Float32MultiArray(data=[float(b) for b in shape]))
                try:
                    self.page.wait_for_function(rebuilt, timeout=3000)
                    break
                except self.PageTimeout:
                    if time.monotonic() > deadline:
                        raise
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            stamp = self._publish(rotvecs, root)
            time.sleep(0.1)
            for _ in range(30):
                state = self.state()
                if {m["garment"] for m in state.values()} >= {"body", "tshirt", "trousers"} and all(
                        m["stamp"] is not None and abs(m["stamp"] - stamp) < 1e-6 for m in state.values()):
                    break
                time.sleep(0.1)
            else:
                continue
            try:
                self.page.wait_for_function(
                    f"() => Object.values(agentdressLook.stamps()).every((s) => s !== null && "
                    f"Math.abs(s - {stamp!r}) < 1e-6)"
                    f" && Object.keys(agentdressLook.stamps()).length >= {len(state)}", timeout=60_000)
                return
            except Exception:
                continue
        raise RuntimeError("the frame did not reach the page:\n" + "\n".join(
            f"{n}: {c.output()[-2000:]}" for n, c in self.children.items()))

    def set_whole_body(self, faces: np.ndarray):
        self.page.evaluate("(faces) => agentdressLook.setWholeBody(faces)", np.asarray(faces).ravel().tolist())

    def hide(self, faces: np.ndarray):
        self.page.evaluate("(faces) => agentdressLook.hide(faces)", np.asarray(faces).ravel().tolist())

    def capture(self, views=VIEWS) -> dict:
        return self.page.evaluate("([views, size]) => agentdressLook.capture(views, size)", [list(views), SIZE])


# ---- the check -----------------------------------------------------------------------------------------------------
def frame_report(captured: dict) -> tuple[list[dict], dict]:
    """(per view counts with masks, per garment edge roughness {key: {mean_mm, max_mm, turning_mean_deg,
    turning_max_deg}}) of one captured frame."""
    from ..display.models import TEMPLATE_LAYERS

    garments = drawn_garments(captured)
    layers = {key: TEMPLATE_LAYERS.get(key.rsplit("/", 1)[-1], 0) for key in garments}
    shells = {key: Shell(*mesh) for key, mesh in garments.items()}
    views = []
    for view in decode_capture(captured):
        counts = view_counts(view["shown"], view["reference"], view["depth"], view["matrix"], captured["classes"],
                             shells, layers)
        counts.update(view=view["view"], shown=view["shown"])
        views.append(counts)
    edges = {}
    for key, (vertices, faces) in garments.items():
        distances, turns = [], []
        for loop in boundary_loops(faces):
            d, t = edge_roughness(vertices, loop)
            distances.append(d)
            turns.append(t)
        if distances:
            d, t = np.concatenate(distances), np.concatenate(turns)
            edges[key.rsplit("/", 1)[-1]] = {"mean_mm": float(d.mean()), "max_mm": float(d.max()),
                                            "turning_mean_deg": float(t.mean()), "turning_max_deg": float(t.max())}
    return views, edges


def frames_of(clips, shapes, frames_per_clip: int, fps: float = 30.0):
    """[(clip name, frame index, rotvecs (B, 3), root (3,), shape (6,))]: `frames_per_clip` frames spread evenly over
    each clip (procedural motion names or CMU clip stems in ../shared/mocap/cmu), each clip on each shape."""
    from ..ros.demo import load_clip

    out = []
    for name in clips:
        path = ROOT.parent / "shared" / "mocap" / "cmu" / f"{name}.bvh"
        motion = load_clip(str(path) if path.is_file() else name, fps)
        first = 1 if path.is_file() else 0  # frame 0 of a CMU clip is the conversion's T-pose
        picks = np.linspace(first, len(motion.rotvecs) - 1, frames_per_clip).round().astype(int)
        root = motion.root_translation - motion.root_translation[:1] * np.array([1.0, 1.0, 0.0])
        for shape in shapes:
            out += [(name, int(f), motion.rotvecs[f], root[f], shape) for f in picks]
    return out


def contact_sheet(worst: list, path: Path, kind: str, columns: int = 4, tile: int = 256):
    """A PNG of the worst views of one kind: [(share, label, shown (H, W) classes, mask (H, W))], the counted
    pixels in magenta (grown by one pixel so a thin crack shows at half size), cropped to the agent."""
    from PIL import Image, ImageDraw

    rows = max(1, -(-len(worst) // columns))
    sheet = Image.new("RGB", (columns * tile, rows * (tile + 16)), (16, 16, 16))
    draw = ImageDraw.Draw(sheet)
    for n, (share, label, shown, mask) in enumerate(worst):
        image = SHEET_COLORS[np.minimum(shown, len(SHEET_COLORS) - 1)]
        grown = mask | np.roll(mask, 1, 0) | np.roll(mask, -1, 0) | np.roll(mask, 1, 1) | np.roll(mask, -1, 1)
        image[grown] = MARK
        picture = Image.fromarray(image[::-1].copy())  # rows top down
        sheet.paste(picture.resize((tile, tile), Image.NEAREST), ((n % columns) * tile, (n // columns) * (tile + 16)))
        draw.text(((n % columns) * tile + 4, (n // columns) * (tile + 16) + tile + 2),
                  f"{kind} {100 * share:.2f}% {label}", fill=(230, 230, 230))
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)


def check(clips=("walk",), shapes=None, frames_per_clip: int = 10, views=VIEWS, workdir=None, sheet=None,
          hide_faces=None, data=ROOT / "data", log=None) -> dict:
    """Run the check over clips x shapes x frames_per_clip frames and `views`; the report (JSON-able). sheet: a path
    prefix for the contact sheets (<prefix>_<kind>.png); hide_faces (H, 3): body faces left out of the shown body
    on purpose."""
    import tempfile

    from ..body import AnnyBody
    from ..models.garment_models import BodyModel

    shapes = [None] if shapes is None else [tuple(s) for s in shapes]  # None: the node's default shape
    frames = frames_of(clips, shapes, frames_per_clip)
    whole = BodyModel(AnnyBody()).faces
    shares = {kind: [] for kind in KINDS}
    edges, fills, worst, rows = {}, [], {kind: [] for kind in KINDS}, []
    started = time.monotonic()
    workdir = Path(workdir or tempfile.mkdtemp(prefix="agentdress_look_"))
    with LookSession(workdir, data) as session:
        session.set_whole_body(whole)
        if hide_faces is not None:
            session.hide(hide_faces)
        for n, (clip, index, rotvecs, root, shape) in enumerate(frames):
            session.show(rotvecs, root, shape, timeout=900.0 if n == 0 else 300.0)  # the first: the node starts
            captured = session.capture(views)
            counts, frame_edges = frame_report(captured)
            for garment, e in frame_edges.items():
                for name, value in e.items():
                    edges.setdefault(garment, {}).setdefault(name, []).append(value)
            for v, c in enumerate(counts):
                fills.append(c["fill"])
                row = {"clip": clip, "frame": index, "shape": None if shape is None else list(shape), "view": v,
                       "silhouette": c["silhouette"]}
                for kind in KINDS:
                    share = c[kind] / max(c["silhouette"], 1)
                    shares[kind].append(share)
                    row[kind] = c[kind]
                    item = (share, n * len(views) + v, f"{clip}#{index} view {v}", c["shown"], c["masks"][kind])
                    if c[kind] and (len(worst[kind]) < WORST or share > worst[kind][0][0]):
                        (heapq.heappush if len(worst[kind]) < WORST else heapq.heapreplace)(worst[kind], item)
                rows.append(row)
            if log:
                log(f"frame {n + 1}/{len(frames)} {clip}#{index}: " + ", ".join(
                    f"{kind} {max(c[kind] for c in counts)}" for kind in KINDS))
        errors = list(session.errors)
    codes = getattr(session, "codes", {})
    report = {
        "frames": len(frames), "views": list(views), "clips": list(clips),
        "shapes": [None if s is None else list(s) for s in shapes],
        "image": SIZE, "frame_views": len(rows), "seconds": time.monotonic() - started,
        "share_of_silhouette": {kind: summary(shares[kind]) for kind in KINDS},
        "frame_views_with_any": {kind: int(sum(r[kind] > 0 for r in rows)) for kind in KINDS},
        "edge_roughness": {g: {name: summary(values) for name, values in e.items()} for g, e in edges.items()},
        "edge_sigma_m": SIGMA, "fill_min": float(min(fills)) if fills else None, "page_errors": errors,
        "exit_codes": codes, "per_view": rows,
    }
    if sheet is not None:
        report["contact_sheets"] = {}
        for kind in KINDS:
            ranked = sorted(worst[kind], key=lambda item: -item[0])
            path = Path(f"{sheet}_{kind}.png")
            contact_sheet([(s, label, shown, mask) for s, _, label, shown, mask in ranked], path, kind)
            report["contact_sheets"][kind] = str(path)
    return report


def main(argv=None) -> int:
    from ..offline.sequences import TEST_CLIPS
    from ..motion.procedural import motion_names
    from ..ros.demo import sweep_shape

    parser = argparse.ArgumentParser(prog="agentdress bench look", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--full", action="store_true", help="the full coverage: the 10 test clips of "
                        "../shared/mocap/README.md and every procedural motion, 3 shapes (both ends and the middle of "
                        "the demo's shape sweep), --frames frames per clip and shape (default then 20: 1,080 frames)")
    parser.add_argument("--clips", nargs="+", default=None, help="procedural motions or CMU clip stems (default walk)")
    parser.add_argument("--frames", type=int, default=None, help="frames per clip and shape (default 10)")
    parser.add_argument("--sweep", type=float, nargs="+", default=None,
                        help="times (s) of the demo's 20 s shape sweep to take shapes at (default: the reference "
                             "shape)")
    parser.add_argument("--views", type=int, default=len(VIEWS), help=f"the first n of the {len(VIEWS)} views")
    parser.add_argument("--sheet", default=None, help="contact sheets <prefix>_<kind>.png")
    parser.add_argument("--out", default=None, help="also write the JSON here")
    parser.add_argument("--per-view", action="store_true", help="keep every frame and view's counts in the JSON")
    args = parser.parse_args(argv)
    clips = args.clips or ((*TEST_CLIPS, *motion_names()) if args.full else ("walk",))
    sweep = args.sweep if args.sweep is not None else ((5.0, 15.0, 0.0) if args.full else None)
    shapes = None if sweep is None else [tuple(float(b) for b in sweep_shape(t, 20.0)) for t in sweep]
    frames = args.frames or (20 if args.full else 10)
    # a SIGTERM (timeout, kill) unwinds like Ctrl-C, so that the node, the viewer and Chromium are stopped too: left
    # running, they kept publishing on their random DDS domain
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    report = check(clips, shapes, frames, VIEWS[:args.views], sheet=args.sheet,
                   log=lambda line: print(line, file=sys.stderr, flush=True))
    if not args.per_view:
        report.pop("per_view")
    print(json.dumps(report, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
