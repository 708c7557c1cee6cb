"""The display server: HTTPS + WebSocket on one port (the `websockets` library), serving the three.js client of web/
and streaming the scene's frames to it. No ROS here: the ROS bridge (agentdress_ros.ros.viewer) fills the scene.

Access: a random token is the first path segment of every URL - https://HOST:PORT/<token>/ is the page, and every
relative URL it loads (its modules, three.js, the socket `ws`) carries it. Any request without it gets 403, a
malformed one 400, anything but GET 405; bytes that are not HTTP at all close the connection (the `websockets`
handshake parser); a WebSocket message that is not a valid shape gets an "error" message back.

  /<token>/                      the client (web/index.html)
  /<token>/src/<file>            its modules (web/src)
  /<token>/three/<path>          the pinned three.js package (web/node_modules/three: build/ and examples/jsm/)
  /<token>/state.json            {key: {agent, garment, vertices, faces, frames, stamp, skinned}} (scripts, tests)
  /<token>/ws                    WebSocket: binary mesh and frame messages (display/scene.py), JSON text messages
                                 {"type": "hello" | "status" | "remove" | "error"}; the client sends
                                 {"type": "shape", "agent", "values": [6 phenotypes in [0, 1]]}
"""
from __future__ import annotations

import asyncio
import hmac
import json
import math
import mimetypes
import secrets
import ssl
import threading
from http import HTTPStatus
from pathlib import Path
from urllib.parse import unquote, urlsplit

from websockets.asyncio.server import serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Response

from .state import DisplayScene

__all__ = ["DisplayServer", "NpmMissing", "web_root"]

ROOT = Path(__file__).resolve().parents[2]
THREE_PARTS = ("build", "examples/jsm")  # what of the three package the client may load
# Frame messages to one client at most this often: each carries every mesh that changed since the last, so a crowd
# whose meshes change one by one (30 meshes at 90 Hz: 2,700 changes a second) goes out as ~120 messages, not 2,700,
# and each mesh still reaches the client at the node's rate.
MAX_FRAME_RATE_HZ = 120.0
TYPES = {".js": "text/javascript; charset=utf-8", ".html": "text/html; charset=utf-8", ".css": "text/css",
         ".json": "application/json"}


class NpmMissing(RuntimeError):
    """three.js is not installed beside the client: the message says what to run."""


def web_root(path=None) -> Path:
    """The client's folder (web/ of the checkout, or `path`); NpmMissing when its three.js package is absent."""
    root = Path(path) if path is not None else ROOT / "web"
    if not (root / "node_modules" / "three" / "build" / "three.module.js").is_file():
        raise NpmMissing(f"three.js is not installed in {root / 'node_modules'}: run `make web` (npm ci in {root}; "
                         "Node.js and npm are needed: Debian/Ubuntu `apt-get install -y nodejs npm`, or "
                         "https://nodejs.org)")
    return root


def _response(status: int, body: bytes, content_type: str = "text/plain; charset=utf-8", extra=()) -> Response:
    headers = Headers([("Content-Type", content_type), ("Content-Length", str(len(body))),
                       ("Cache-Control", "no-store"), ("X-Content-Type-Options", "nosniff"), ("Connection", "close"),
                       *extra])
    return Response(status, HTTPStatus(status).phrase, headers, body)


class DisplayServer:
    """Serve `scene` to clients on host:port (port 0: any free one) from the web root; TLS when cert/key given.

    on_shape(agent, values (6,)): called on the server's thread when a client moves a shape slider."""

    def __init__(self, scene: DisplayScene, web: Path, host: str = "127.0.0.1", port: int = 8765,
                 certificate=None, token: str | None = None, on_shape=None, phenotypes=()):
        self.scene, self.web, self.host, self.port = scene, Path(web), host, port
        self.token = token or secrets.token_urlsafe(18)
        self.on_shape, self.phenotypes = on_shape, list(phenotypes)
        self.ssl = None
        if certificate is not None:
            self.ssl = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            self.ssl.load_cert_chain(*map(str, certificate))
        self._loop = None
        self._server = None
        self._ready = threading.Event()
        self._thread = None
        self._error = None

    # ---- lifecycle -----------------------------------------------------------------------------------------------
    def start(self) -> int:
        """Start serving on a thread of its own; returns the bound port. Raises OSError if it cannot listen."""
        self._thread = threading.Thread(target=self._run, name="agentdress-display", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise self._error
        return self.port

    def url(self, host: str | None = None) -> str:
        shown = host or ("127.0.0.1" if self.host in ("0.0.0.0", "", "::") else self.host)
        return f"{'https' if self.ssl else 'http'}://{shown}:{self.port}/{self.token}/"

    def stop(self):
        if self._loop is not None and self._server is not None:
            self._loop.call_soon_threadsafe(self._server.close)
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def _run(self):
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._serve())
        except OSError as error:
            self._error = error
            self._ready.set()
        finally:
            loop.close()

    async def _serve(self):
        async with serve(self._client, self.host, self.port, ssl=self.ssl, process_request=self._http,
                         compression=None, max_size=2**16, server_header="agentdress") as server:
            self._server = server
            self.port = next(iter(server.sockets)).getsockname()[1]
            self._ready.set()
            await server.wait_closed()

    # ---- HTTP ----------------------------------------------------------------------------------------------------
    def _http(self, connection, request):
        """Static files, the state, or (for /<token>/ws with an upgrade) None to go on with the handshake."""
        if request.method != "GET":
            return _response(405, b"method not allowed: GET only", extra=[("Allow", "GET")])
        try:
            path = urlsplit(request.path).path
        except ValueError:
            return _response(400, b"bad request: malformed path")
        parts = path.split("/", 2)  # "", token, rest
        if len(parts) < 2 or not hmac.compare_digest(parts[1].encode(), self.token.encode()):
            return _response(403, b"forbidden: the URL printed at start (with its access token) is needed")
        if len(parts) == 2:
            return _response(302, b"", extra=[("Location", f"/{self.token}/")])
        rest = unquote(parts[2])
        if rest == "ws":
            if request.headers.get("Upgrade", "").lower() != "websocket":
                return _response(400, b"bad request: /ws is a WebSocket endpoint")
            return None
        if rest == "state.json":
            return _response(200, json.dumps(self.scene.summary()).encode(), TYPES[".json"])
        file = self._file(rest)
        if file is None:
            return _response(404, b"not found")
        return _response(200, file.read_bytes(), TYPES.get(file.suffix) or mimetypes.guess_type(file.name)[0]
                         or "application/octet-stream")

    def _file(self, rest: str) -> Path | None:
        if rest in ("", "index.html"):
            candidate, allowed = self.web / "index.html", [self.web]
        elif rest.startswith("src/"):
            candidate, allowed = self.web / rest, [self.web / "src"]
        elif rest.startswith("three/"):
            three = self.web / "node_modules" / "three"
            candidate, allowed = three / rest[len("three/"):], [three / part for part in THREE_PARTS]
        else:
            return None
        candidate = candidate.resolve()
        if not candidate.is_file() or not any(candidate.is_relative_to(a.resolve()) for a in allowed):
            return None
        return candidate

    # ---- WebSocket -----------------------------------------------------------------------------------------------
    async def _client(self, websocket):
        loop = asyncio.get_running_loop()
        event = asyncio.Event()

        def wake():  # from the ROS thread: at most one pending wake-up per client
            if not event.is_set():
                loop.call_soon_threadsafe(event.set)

        self.scene.add_listener(wake)
        receiver = asyncio.create_task(self._receive(websocket))
        seen: dict = {}
        last_frame = -math.inf
        try:
            await websocket.send(json.dumps({"type": "hello", "phenotypes": self.phenotypes}))
            while not receiver.done():
                wait = last_frame + 1.0 / MAX_FRAME_RATE_HZ - loop.time()
                if wait > 0:
                    await asyncio.sleep(wait)  # changes meanwhile gather into the next message
                event.clear()
                meshes, removed, frame, statuses = self.scene.updates(seen)
                for message in meshes:
                    await websocket.send(message)
                for key in removed:
                    await websocket.send(json.dumps({"type": "remove", "key": key}))
                if frame is not None:
                    last_frame = loop.time()
                    await websocket.send(frame)  # waits while the client is behind: frames coalesce, never queue
                for status in statuses:
                    await websocket.send(json.dumps(status))
                try:
                    await asyncio.wait_for(event.wait(), 1.0)
                except TimeoutError:
                    pass
        except ConnectionClosed:
            pass
        finally:
            self.scene.remove_listener(wake)
            receiver.cancel()

    async def _receive(self, websocket):
        async for text in websocket:
            try:
                agent, values = self._shape_message(text)
            except ValueError as error:
                await websocket.send(json.dumps({"type": "error", "message": str(error)}))
                continue
            if self.on_shape is not None:
                try:
                    self.on_shape(agent, values)
                except Exception as error:  # a failed publish is reported to the page, never ends the server
                    await websocket.send(json.dumps({"type": "error", "message": f"shape not sent: {error}"}))

    def _shape_message(self, text) -> tuple[str, list[float]]:
        if not isinstance(text, str):
            raise ValueError("expected a JSON text message")
        try:
            message = json.loads(text)
        except json.JSONDecodeError as error:
            raise ValueError(f"not JSON: {error}") from None
        if not isinstance(message, dict) or message.get("type") != "shape":
            raise ValueError("expected {\"type\": \"shape\", \"agent\": ..., \"values\": [...]}")
        agent, values = message.get("agent"), message.get("values")
        count = len(self.phenotypes) or 6
        if not isinstance(agent, str) or not isinstance(values, list) or len(values) != count or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values):
            raise ValueError(f"a shape needs an agent name and {count} finite numbers")
        return agent, [min(1.0, max(0.0, float(v))) for v in values]
