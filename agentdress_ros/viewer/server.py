"""The display server: HTTPS + WebSocket on one port (the `websockets` library), serving the three.js client of web/
and streaming the scene's frames to it. No ROS here: the ROS bridge (agentdress_ros.ros.viewer) fills the scene.

Access: a random token is the first path segment of every URL - https://HOST:PORT/<token>/ is the page, and every
relative URL it loads (its modules, three.js, the socket `ws`) carries it. Any request without it gets 403, a
malformed one 400, a file path the system cannot open (a null byte, a name too long, a link loop) 404 with one
line logged, anything but GET 405; bytes that are not HTTP at all, or bytes after a request, close the connection
(the `websockets` handshake parser); a WebSocket from a page of another origin (its Origin header is not the
request's Host) gets 403. Every answer carries a Content-Security-Policy that allows the page's own files only (and
its inline import map by hash), X-Frame-Options DENY and Referrer-Policy no-referrer (the token is in the URL).

A WebSocket message that is not a valid shape gets an "error" message back (not JSON, nested too deep, numbers too
large, an agent the viewer does not show); a shape with values out of [0, 1] is clamped and a "warning" says so.
Shapes go out at most `shape_rate_hz` per client, the latest per agent winning, on a worker thread (the callback
may look up the ROS graph). A client whose frames stay unsent for `send_timeout_s` (it stopped reading) is dropped,
and at most `max_clients` sockets are served at once: one more is closed with code 1013 (try again later).

  /<token>/                      the client (web/index.html)
  /<token>/src/<file>            its modules (web/src)
  /<token>/three/<path>          the pinned three.js package (web/node_modules/three: build/ and examples/jsm/)
  /<token>/lil-gui.css           the styles of three's lil-gui (the panel), taken from its module: lil-gui would
                                 inject them as a <style>, which the page's policy does not allow
  /<token>/state.json            {key: {agent, garment, vertices, faces, frames, stamp, skinned}} (scripts, tests)
  /<token>/ws                    WebSocket: binary mesh and frame messages (viewer/state.py), JSON text messages
                                 {"type": "hello" | "status" | "remove" | "error" | "warning"}; the client sends
                                 {"type": "shape", "agent", "values": [6 phenotypes in [0, 1]]}
"""
from __future__ import annotations

import asyncio
import base64
import hashlib
import hmac
import json
import logging
import math
import mimetypes
import re
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
from .tls import server_context

__all__ = ["DisplayServer", "NpmMissing", "web_root"]

log = logging.getLogger("agentdress.display")

ROOT = Path(__file__).resolve().parents[2]
THREE_PARTS = ("build", "examples/jsm")  # what of the three package the client may load
# Frame messages to one client at most this often: each carries every mesh that changed since the last, so a crowd
# whose meshes change one by one (30 meshes at 90 Hz: 2,700 changes a second) goes out as ~120 messages, not 2,700,
# and each mesh still reaches the client at the node's rate.
MAX_FRAME_RATE_HZ = 120.0
SHAPE_RATE_HZ = 10.0  # shape messages published per client at most (the page sends one per 100 ms of dragging)
SEND_TIMEOUT_S = 10.0  # a client whose frame stays unsent this long has stopped reading: it is dropped
MAX_CLIENTS = 8  # WebSockets served at once (a headset or two and a few pages)
TRY_AGAIN_LATER = 1013  # the WebSocket close code for a server at its limit (RFC 6455, IANA registry)
LIL_GUI = "examples/jsm/libs/lil-gui.module.min.js"
# lil-gui (0.17, three 0.187) injects its styles from a string literal: function(t){const i=document.createElement(
# "style");i.innerHTML=t;...}('<css>')
LIL_GUI_STYLES = re.compile(r"""createElement\("style"\);\w+\.innerHTML=\w+;.*?\}\('((?:[^'\\]|\\.)*)'\)""",
                            re.DOTALL)
IMPORT_MAP = re.compile(rb'<script type="importmap">(.*?)</script>', re.DOTALL)
TYPES = {".js": "text/javascript; charset=utf-8", ".html": "text/html; charset=utf-8",
         ".css": "text/css; charset=utf-8", ".json": "application/json"}


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


def content_security_policy(index_html: bytes) -> str:
    """What the page may load: its own scripts, worker, styles and socket, plus its inline import map by hash
    (sha256 of the script's text); images from itself or data: URLs (the favicon), fonts from data: URLs (lil-gui's
    icons are a font inside its styles), nothing else."""
    scripts = "".join(f" 'sha256-{base64.b64encode(hashlib.sha256(m).digest()).decode()}'"
                      for m in IMPORT_MAP.findall(index_html))
    return (f"default-src 'none'; script-src 'self'{scripts}; style-src 'self'; img-src 'self' data:; "
            "connect-src 'self'; worker-src 'self'; font-src data:; base-uri 'none'; form-action 'none'; "
            "frame-ancestors 'none'")


def lil_gui_styles(module: str) -> str | None:
    """The style sheet lil-gui's module would inject (its escapes undone), or None when the module has none."""
    match = LIL_GUI_STYLES.search(module)
    return re.sub(r"\\(.)", r"\1", match.group(1)) if match else None


class _SlowClient(Exception):
    """A frame stayed unsent past the timeout: the client no longer reads."""


class DisplayServer:
    """Serve `scene` to clients on host:port (port 0: any free one) from the web root; TLS when cert/key given.

    certificate: (cert path, key path) (CertificateError, saying which file is wrong, when they do not load) or
    an ssl.SSLContext. on_shape(agent, values (6,)): called on a worker thread when a client moves a shape slider,
    for agents the scene shows only, at most shape_rate_hz per client."""

    def __init__(self, scene: DisplayScene, web: Path, host: str = "127.0.0.1", port: int = 8765,
                 certificate=None, token: str | None = None, on_shape=None, phenotypes=(),
                 shape_rate_hz: float = SHAPE_RATE_HZ, send_timeout_s: float = SEND_TIMEOUT_S,
                 max_clients: int = MAX_CLIENTS):
        self.scene, self.web, self.host, self.port = scene, Path(web), host, port
        self.token = token or secrets.token_urlsafe(18)
        self.on_shape, self.phenotypes = on_shape, list(phenotypes)
        self.shape_interval_s, self.send_timeout_s, self.max_clients = 1.0 / shape_rate_hz, send_timeout_s, max_clients
        self.clients = 0  # WebSockets served now
        self.ssl = certificate if isinstance(certificate, ssl.SSLContext) or certificate is None \
            else server_context(*certificate)
        self._policy = (None, "")  # (index.html's mtime and size, its Content-Security-Policy)
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
    def _response(self, status: int, body: bytes, content_type: str = "text/plain; charset=utf-8",
                  extra=()) -> Response:
        headers = Headers([("Content-Type", content_type), ("Content-Length", str(len(body))),
                           ("Cache-Control", "no-store"), ("X-Content-Type-Options", "nosniff"),
                           ("Content-Security-Policy", self._security_policy()), ("X-Frame-Options", "DENY"),
                           ("Referrer-Policy", "no-referrer"), ("Connection", "close"), *extra])
        return Response(status, HTTPStatus(status).phrase, headers, body)

    def _security_policy(self) -> str:
        """The policy of the current index.html (its import map's hash), read again when the file changes."""
        index = self.web / "index.html"
        try:
            info = index.stat()
            version = (info.st_mtime_ns, info.st_size)
            if version != self._policy[0]:
                self._policy = (version, content_security_policy(index.read_bytes()))
        except OSError:
            self._policy = (None, content_security_policy(b""))
        return self._policy[1]

    def _http(self, connection, request):
        """Static files, the state, or (for /<token>/ws with an upgrade) None to go on with the handshake."""
        if connection.protocol.eof_sent:  # bytes after the request (pipelining) already failed the connection
            return self._abandon(connection)
        if request.method != "GET":
            return self._response(405, b"method not allowed: GET only", extra=[("Allow", "GET")])
        try:
            path = urlsplit(request.path).path
        except ValueError:
            return self._response(400, b"bad request: malformed path")
        parts = path.split("/", 2)  # "", token, rest
        if len(parts) < 2 or not hmac.compare_digest(parts[1].encode(), self.token.encode()):
            return self._response(403, b"forbidden: the URL printed at start (with its access token) is needed")
        if len(parts) == 2:
            return self._response(302, b"", extra=[("Location", f"/{self.token}/")])
        rest = unquote(parts[2])
        if rest == "ws":
            if request.headers.get("Upgrade", "").lower() != "websocket":
                return self._response(400, b"bad request: /ws is a WebSocket endpoint")
            origin = request.headers.get("Origin")  # sent by browsers: a page elsewhere must not use the token
            if origin is not None and urlsplit(origin).netloc.lower() != request.headers.get("Host", "").lower():
                log.warning("WebSocket from origin %.100r refused (host %.100r)", origin, request.headers.get("Host"))
                return self._response(403, b"forbidden: a WebSocket from a page of another origin")
            return None
        if rest == "lil-gui.css":
            return self._lil_gui_styles()
        if rest == "state.json":
            return self._response(200, json.dumps(self.scene.summary()).encode(), TYPES[".json"])
        try:
            file = self._file(rest)
            body = file.read_bytes() if file is not None else None
        except (ValueError, OSError, RuntimeError) as error:  # null byte; name too long, unreadable; link loop
            log.warning("request for %.100r not served: %s", rest, f"{type(error).__name__}: {error}"[:200])
            body = None
        if body is None:
            return self._response(404, b"not found")
        return self._response(200, body, TYPES.get(file.suffix) or mimetypes.guess_type(file.name)[0]
                              or "application/octet-stream")

    def _lil_gui_styles(self) -> Response:
        module = self.web / "node_modules" / "three" / LIL_GUI
        try:
            styles = lil_gui_styles(module.read_text(encoding="utf-8"))
        except OSError as error:
            log.warning("lil-gui's styles not served: %s", error)
            styles = None
        if styles is None:
            log.warning("no styles found in %s: the panel shows unstyled", module)
            return self._response(404, b"not found")
        return self._response(200, styles.encode(), TYPES[".css"])

    async def _abandon(self, connection):
        """Close a connection whose request was followed by more bytes, answering nothing: websockets read them as
        frames of a socket not yet open, failed it, and would fail an assertion sending its answer (websockets
        17.4). Once the transport is closed, the handshake sends nothing."""
        log.info("connection %s closed: bytes after its request", connection.remote_address)
        connection.transport.abort()
        await asyncio.sleep(0)  # connection_lost runs: the connection is CLOSED
        return self._response(400, b"bad request: bytes after the request")

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
        if self.clients >= self.max_clients:
            log.warning("WebSocket refused: %d served already (the limit)", self.clients)
            await websocket.close(TRY_AGAIN_LATER, f"the viewer serves {self.max_clients} clients at most: try later")
            return
        self.clients += 1
        loop = asyncio.get_running_loop()
        event = asyncio.Event()

        def wake():  # from the ROS thread: at most one pending wake-up per client
            if not event.is_set():
                loop.call_soon_threadsafe(event.set)

        self.scene.add_listener(wake)
        shapes: dict = {}  # agent -> the latest values not yet handed to on_shape
        shape_waiting = asyncio.Event()
        receiver = asyncio.create_task(self._receive(websocket, shapes, shape_waiting))
        publisher = asyncio.create_task(self._publish_shapes(websocket, shapes, shape_waiting))
        seen: dict = {}
        last_frame = -math.inf
        try:
            await self._send(websocket, json.dumps({"type": "hello", "phenotypes": self.phenotypes}))
            while not receiver.done():
                wait = last_frame + 1.0 / MAX_FRAME_RATE_HZ - loop.time()
                if wait > 0:
                    await asyncio.sleep(wait)  # changes meanwhile gather into the next message
                event.clear()
                meshes, removed, frame, statuses = self.scene.updates(seen)
                for message in meshes:
                    await self._send(websocket, message)
                for key in removed:
                    await self._send(websocket, json.dumps({"type": "remove", "key": key}))
                if frame is not None:
                    last_frame = loop.time()
                    await self._send(websocket, frame)  # waits while the client is behind: frames coalesce
                for status in statuses:
                    await self._send(websocket, json.dumps(status))
                try:
                    await asyncio.wait_for(event.wait(), 1.0)
                except TimeoutError:
                    pass
        except ConnectionClosed:
            pass
        except _SlowClient:
            self._drop(websocket)
        finally:
            self.clients -= 1
            self.scene.remove_listener(wake)
            receiver.cancel()
            publisher.cancel()

    async def _send(self, websocket, message):
        """Send, or _SlowClient once the message stays unsent for send_timeout_s (the client stopped reading)."""
        try:
            async with asyncio.timeout(self.send_timeout_s):
                await websocket.send(message)
        except TimeoutError:
            raise _SlowClient from None

    def _drop(self, websocket):
        log.warning("client %s dropped: a message stayed unsent for %.0f s", websocket.remote_address,
                    self.send_timeout_s)
        websocket.transport.abort()

    async def _receive(self, websocket, shapes: dict, shape_waiting: asyncio.Event):
        """Validate each message; a valid shape replaces that agent's pending one (the latest wins)."""
        try:
            async for text in websocket:
                try:
                    agent, values, clamped = self._shape_message(text)
                except ValueError as error:
                    await self._send(websocket, json.dumps({"type": "error", "message": str(error)}))
                    continue
                if clamped:
                    await self._send(websocket, json.dumps({"type": "warning", "message": clamped}))
                shapes[agent] = values
                shape_waiting.set()
        except _SlowClient:
            self._drop(websocket)

    async def _publish_shapes(self, websocket, shapes: dict, shape_waiting: asyncio.Event):
        """Hand the pending shapes to on_shape at most once per shape interval, on a worker thread: the callback
        may look up the ROS graph or block on a publish, which must not stall the frames of every client."""
        if self.on_shape is None:
            return
        try:
            while True:
                await shape_waiting.wait()
                shape_waiting.clear()
                pending = list(shapes.items())
                shapes.clear()
                for agent, values in pending:
                    try:
                        await asyncio.to_thread(self.on_shape, agent, values)
                    except Exception as error:  # a failed publish is reported to the page, never ends the server
                        await self._send(websocket, json.dumps({"type": "error",
                                                                "message": f"shape not sent: {error}"}))
                await asyncio.sleep(self.shape_interval_s)
        except (_SlowClient, ConnectionClosed):
            pass

    def _shape_message(self, text) -> tuple[str, list[float], str]:
        """(agent, values clamped to [0, 1], '' or what was clamped); ValueError saying what is wrong."""
        if not isinstance(text, str):
            raise ValueError("expected a JSON text message")
        try:
            message = json.loads(text)
        except RecursionError:
            raise ValueError("not JSON this viewer reads: nested too deep") from None
        except ValueError as error:  # not JSON, or an integer of more digits than Python converts
            raise ValueError(f"not JSON: {error}"[:300]) from None
        if not isinstance(message, dict) or message.get("type") != "shape":
            raise ValueError("expected {\"type\": \"shape\", \"agent\": ..., \"values\": [...]}")
        agent, values = message.get("agent"), message.get("values")
        count = len(self.phenotypes) or 6
        numbers = [_finite(v) for v in values] if isinstance(values, list) and len(values) == count else None
        if not isinstance(agent, str) or numbers is None or None in numbers:
            raise ValueError(f"a shape needs an agent name and {count} finite numbers")
        known = sorted({mesh["agent"] for mesh in self.scene.summary().values()})
        if agent not in known:
            raise ValueError(f"no agent {agent[:100]!r} in this viewer (it shows {', '.join(known[:20]) or 'none'})")
        clamped = [min(1.0, max(0.0, v)) for v in numbers]
        changed = [f"{self.phenotypes[i] if self.phenotypes else i} {v:g} -> {c:g}"
                   for i, (v, c) in enumerate(zip(numbers, clamped)) if v != c]
        return agent, clamped, ("shape values outside [0, 1] clamped: " + ", ".join(changed)) if changed else ""


def _finite(value) -> float | None:
    """A JSON number as a finite float, or None (not a number, a bool, NaN, infinite, or an integer past float)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None
