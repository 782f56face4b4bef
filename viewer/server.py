"""The viewer's local HTTP server (127.0.0.1 only): the page, its vendored libraries, and a small JSON/binary API over
`SceneData`. The page loads nothing from anywhere else.

Only the viewer's own page can drive it (docs/viewer-security.md): every request for data or a change carries the
token of this server start (printed in the URL); the Host must be this server's own (no DNS rebinding); a POST must
be `application/json` from this server's own Origin; the page runs under a strict Content-Security-Policy."""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import logging
import math
import mimetypes
import re
import secrets
import shlex
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlparse

from fullview.io.config import Config
from fullview.io.dataset import Dataset
from fullview.io.errors import FullviewError
from fullview.stages.runner import Pipeline
from fullview.viewer.scene import RequestError, SceneData

log = logging.getLogger(__name__)

WEB = Path(__file__).resolve().parent / "web"
VENDOR = WEB / "node_modules"
VENDORED = ("three", "@photo-sphere-viewer")  # the only packages the page may load
MAX_BODY = 8 << 20  # bytes of a POSTed hand_points document
HAND_CHECK_FACTOR = 4.0  # a hand point farther than this many filter thresholds from its epipolar circle is flagged
TOKEN_HEADER = "X-Fullview-Token"  # the page sends the token in this header; <img> URLs carry it as ?token=
TOKEN_BYTES = 32  # random bytes of a server start's token (secrets' recommendation for a URL-safe secret)
REQUEST_TIMEOUT_S = 30  # a client that stops sending mid-request is dropped after this long (frees its thread)
SHELL = ("/", "/index.html")  # the page shell, served without the token (it holds no workspace data)
SHELL_PREFIXES = ("/static/", "/vendor/")  # the page's own code and the vendored libraries, likewise


def _import_map_hash() -> str:
    """CSP source of the page's one inline script, its import map (data, not code): 'sha256-<base64>'."""
    match = re.search(r'<script type="importmap">(.*?)</script>', (WEB / "index.html").read_text(), re.S)
    digest = hashlib.sha256(match.group(1).encode()).digest() if match else b""
    return f"'sha256-{base64.b64encode(digest).decode()}'"


CSP = "; ".join([
    "default-src 'self'",
    f"script-src 'self' {_import_map_hash()}",  # no other inline script, no eval
    "style-src 'self'",
    "img-src 'self' blob: data:",  # the panoramas as blobs (Photo Sphere Viewer), the empty data: favicon
    "connect-src 'self'",
    "object-src 'none'",
    "base-uri 'none'",
    "form-action 'none'",
    "frame-ancestors 'none'",
])
SECURITY_HEADERS = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",  # the token in the page's URL never leaves in a Referer
    "Cross-Origin-Resource-Policy": "same-origin",  # another origin's <img>/<script> gets nothing
    "X-Frame-Options": "DENY",
}


class ViewerApp:
    """State shared by the request handlers: the scene data, the token of this server start and a background
    rerun."""

    def __init__(self, pipeline: Pipeline, config: Config):
        self.pipeline, self.config = pipeline, config
        self.scene = SceneData(pipeline)
        self.token = secrets.token_urlsafe(TOKEN_BYTES)
        self.rerun_thread: threading.Thread | None = None
        self.rerun_message = ""
        self.save_lock = threading.Lock()  # one save at a time: each backup holds the very file its save replaced

    def rerun(self) -> str:
        """Rerun what the hand points changed (filter on), in the background under the workspace lock."""
        if self.rerun_thread is not None and self.rerun_thread.is_alive():
            return "a run is already going"

        def work():
            outcome = "run failed: it stopped without a reason (see the log)"  # kept if something unforeseen raises
            try:
                fresh = Pipeline(Dataset(self.pipeline.dataset.root), self.pipeline.ws, self.config)
                ran = fresh.run(wait=False)
                outcome = f"ran: {', '.join(ran) or 'nothing (all fresh)'}"
            except (FullviewError, OSError) as e:
                where = f"{e.filename}: " if isinstance(e, OSError) and e.filename else ""
                outcome = f"run failed: {where}{e.strerror if isinstance(e, OSError) and e.strerror else e}"
            finally:
                self.rerun_message = outcome  # never "running" once the thread ends
            try:
                self.pipeline.dataset = Dataset(self.pipeline.dataset.root)
                self.scene = SceneData(Pipeline(self.pipeline.dataset, self.pipeline.ws, self.config))
            except FullviewError as e:
                self.rerun_message = f"{outcome}; cannot reload the dataset: {e}"

        self.rerun_message = "running"
        self.rerun_thread = threading.Thread(target=work, daemon=True)
        self.rerun_thread.start()
        return "started"

    def rerun_command(self) -> str:
        """The shell command that reruns what the saved hand points made stale (quoted: names may hold spaces)."""
        root, ws = self.pipeline.dataset.root, self.pipeline.ws
        own = ["-w", str(ws.root.parent)] if ws.workspace_option(root) else []  # the dataset's own workspace: no -w
        return shlex.join(["fullview", "run", str(root), *own])


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    request_queue_size = 64  # listen backlog (socketserver's 5 resets connections when a page opens many at once)

    def handle_error(self, request, client_address):  # socketserver's default prints a traceback to stderr
        log.error("viewer: a request from %s failed outside its handler", client_address[0], exc_info=True)


def make_server(app: ViewerApp, port: int = 0) -> ThreadingHTTPServer:
    handler = type("Handler", (_Handler,), {"app": app})
    return _Server(("127.0.0.1", port), handler)


def page_url(server: ThreadingHTTPServer) -> str:
    """The page's address with this server start's token, as printed and opened."""
    return f"http://127.0.0.1:{server.server_address[1]}/?token={server.RequestHandlerClass.app.token}"


class _Handler(BaseHTTPRequestHandler):
    app: ViewerApp
    server_version = "fullview-viewer"
    timeout = REQUEST_TIMEOUT_S

    def log_message(self, fmt, *args):  # the default writes every request to stderr; the token is not logged
        log.debug("%s %s", self.address_string(), (fmt % args).replace(self.app.token, "<token>"))

    # ---------------------------------------------------------------------------------------------- routing
    def do_GET(self):
        self._answer(self._get)

    def do_POST(self):
        self._answer(self._post)

    def _answer(self, route):
        """Guard, route and answer one request: always a response, a one-line JSON error for anything refused."""
        url = urlparse(self.path)
        path = unquote(url.path)
        try:
            self._guard(path, url.query)
            return route(path, {k: v[0] for k, v in parse_qs(url.query).items()})
        except RequestError as e:
            return self._error(HTTPStatus(e.status), str(e))
        except FullviewError as e:
            return self._error(HTTPStatus.BAD_REQUEST, str(e))
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            self.close_connection = True
        except Exception as e:  # noqa: BLE001 — the server's boundary, like the CLI's: our bug, said in one line
            log.error("viewer: internal error on %s %s: %s: %s", self.command, path, type(e).__name__, e)
            log.debug("traceback", exc_info=True)
            return self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"internal error: {type(e).__name__}")

    def _guard(self, path: str, query: str) -> None:
        """Refuse (RequestError) a request not from the viewer's own page: wrong Host (DNS rebinding), missing or
        wrong token, or a POST that is not same-origin JSON."""
        port = self.server.server_address[1]
        hosts = {f"127.0.0.1:{port}", f"localhost:{port}", f"[::1]:{port}"}
        host = self.headers.get_all("Host") or []
        if len(host) != 1 or host[0].lower() not in hosts:
            raise RequestError(f"Host must be one of {sorted(hosts)}", HTTPStatus.MISDIRECTED_REQUEST)
        if self.command == "POST":
            origin = self.headers.get("Origin")
            if origin is None or origin.lower() != f"http://{host[0].lower()}":
                raise RequestError("a POST must come from the viewer's own page (Origin)", HTTPStatus.FORBIDDEN)
            kind = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
            if kind != "application/json":
                raise RequestError("a POST must be Content-Type: application/json", HTTPStatus.FORBIDDEN)
        elif path in SHELL or path.startswith(SHELL_PREFIXES):
            return  # the page shell: the same for everyone, no workspace data
        given = self.headers.get(TOKEN_HEADER)
        if given is None and self.command == "GET":  # <img> and texture URLs cannot send a header
            given = parse_qs(query).get("token", [None])[0]
        if given is None or not hmac.compare_digest(given.encode("utf-8", "replace"), self.app.token.encode()):
            raise RequestError("missing or wrong token: open the URL `fullview view` printed", HTTPStatus.FORBIDDEN)

    def _get(self, path: str, query: dict):
        scene = self.app.scene
        if path in SHELL:
            return self._file(WEB / "index.html")
        if path.startswith("/static/"):
            return self._file(_inside(WEB, path[len("/static/"):]))
        if path.startswith("/vendor/"):
            rel = path[len("/vendor/"):]
            if not rel.startswith(VENDORED):
                return self._error(HTTPStatus.NOT_FOUND, "not a vendored package")
            return self._file(_inside(VENDOR, rel))
        if path == "/api/generation":  # polled every few seconds: cheap, no status computation
            return self._json({"generation": scene.generation(), "rerun": self.app.rerun_message})
        if path == "/api/state":
            state = scene.state()
            state["rerun"] = self.app.rerun_message
            return self._json(state)
        if path.startswith("/api/points/"):
            kind = path.rsplit("/", 1)[1]
            if kind not in ("sparse", "dense"):
                return self._error(HTTPStatus.NOT_FOUND, "unknown cloud")
            return self._send(scene.points(kind), "application/octet-stream")
        if path == "/api/mesh":
            return self._send(scene.mesh(), "application/octet-stream")
        if path == "/api/matches":
            return self._json(scene.matches(_param(query, "a"), _param(query, "b")))
        if path == "/api/measure":
            return self._json(scene.measure(_param(query, "image"), _point(query, "a"), _point(query, "b")))
        if path == "/api/hand_points":
            tracks = self.app.pipeline.dataset.hand_tracks()
            return self._json([{"name": t.name, "observations": t.observations} for t in tracks])
        if path.startswith("/pano/"):
            width = _param(query, "width", "2048")
            if not (width.isascii() and width.isdigit() and len(width) <= 6):
                raise RequestError(f"width must be a whole number of pixels, got {width[:20]!r}")
            return self._send(scene.panorama_jpeg(scene.image(path[len("/pano/"):]), int(width)), "image/jpeg",
                              cache=True)
        if path.startswith("/depth/"):
            png = scene.depth_png(path[len("/depth/"):])
            return self._send(png, "image/png") if png else self._error(HTTPStatus.NOT_FOUND, "no depth map")
        return self._error(HTTPStatus.NOT_FOUND, "no such page")

    def _post(self, path: str, query: dict):
        if path == "/api/hand_points":
            body = self._body()
            dataset = self.app.pipeline.dataset
            with self.app.save_lock:
                backup = dataset.save_hand_points(body.get("points") if isinstance(body, dict) else None)
            return self._json({"saved": str(dataset.hand_points_path), "backup": str(backup) if backup else None,
                               "command": self.app.rerun_command()})
        if path == "/api/hand_check":
            body = self._body()
            threshold = HAND_CHECK_FACTOR * self.app.config["filter"].threshold_deg
            return self._json({"threshold_deg": threshold, "pairs": self.app.scene.hand_check(
                body.get("points") if isinstance(body, dict) else None, threshold)})
        if path == "/api/rerun":
            self._body()
            return self._json({"rerun": self.app.rerun()})
        return self._error(HTTPStatus.NOT_FOUND, "no such endpoint")

    # ---------------------------------------------------------------------------------------------- helpers
    def _body(self):
        """The request's JSON body; its length is checked before a byte is read."""
        lengths = self.headers.get_all("Content-Length") or []
        if len(lengths) != 1:
            raise RequestError("a POST needs one Content-Length header", HTTPStatus.LENGTH_REQUIRED)
        raw = lengths[0].strip()
        if not (raw.isascii() and raw.isdigit()):
            raise RequestError(f"Content-Length must be a byte count, got {raw[:20]!r}")
        if int(raw) > MAX_BODY:
            raise RequestError(f"request body of {raw[:20]} bytes is over the limit of {MAX_BODY}",
                               HTTPStatus.REQUEST_ENTITY_TOO_LARGE)
        data = self.rfile.read(int(raw))
        if len(data) != int(raw):
            raise RequestError(f"request body ended after {len(data)} of {raw} bytes")
        try:
            return json.loads(data.decode("utf-8") or "null", parse_constant=_no_constant)
        except RecursionError:
            raise RequestError("request body is nested too deeply") from None
        except ValueError as e:  # JSONDecodeError, UnicodeDecodeError, an integer of too many digits
            raise RequestError(f"request body is not JSON: {' '.join(str(e).split())[:200]}") from None

    def _file(self, path: Path | None):
        if path is None or not path.is_file():
            return self._error(HTTPStatus.NOT_FOUND, "no such file")
        kind = mimetypes.guess_type(path.name)[0] or "application/octet-stream"
        if path.suffix in (".js", ".mjs"):
            kind = "text/javascript"
        return self._send(path.read_bytes(), kind, cache=path.is_relative_to(VENDOR))

    def _json(self, obj):
        return self._send(json.dumps(obj).encode(), "application/json")

    def _error(self, status: HTTPStatus, message: str):
        self.close_connection = True  # a refused body may be left unread
        return self._send(json.dumps({"error": " ".join(message.split())}).encode(), "application/json",
                          status=status)

    def _send(self, data: bytes, kind: str, *, status: HTTPStatus = HTTPStatus.OK, cache: bool = False):
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
        for name, value in SECURITY_HEADERS.items():
            self.send_header(name, value)
        self.end_headers()
        self.wfile.write(data)


def _param(query: dict, key: str, default: str | None = None) -> str:
    if key not in query and default is None:
        raise RequestError(f"missing query parameter {key!r}")
    return query.get(key, default)


def _point(query: dict, key: str) -> tuple[float, float]:
    """A pixel given as `key=x,y` (two finite numbers)."""
    text = _param(query, key)
    parts = text.split(",")
    try:
        x, y = (float(v) for v in parts) if len(parts) == 2 else (None, None)
    except ValueError:
        x = y = None
    if x is None or not (math.isfinite(x) and math.isfinite(y)):
        raise RequestError(f"{key} must be a pixel x,y (two finite numbers), got {text[:40]!r}")
    return x, y


def _no_constant(name: str):
    raise RequestError(f"request body is not strict JSON: {name} is not a number JSON allows")


def _inside(root: Path, rel: str) -> Path | None:
    """`root / rel` when it stays inside `root` (no '..' escapes), else None."""
    path = (root / rel).resolve()
    return path if path.is_relative_to(root.resolve()) else None
