"""The viewer's local HTTP server (127.0.0.1 only): the page, its vendored libraries, and a small JSON/binary API over
`SceneData`. The page loads nothing from anywhere else."""

from __future__ import annotations

import json
import logging
import mimetypes
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlparse

from fullview.io.config import Config
from fullview.io.dataset import Dataset
from fullview.io.errors import FullviewError
from fullview.stages.runner import Pipeline
from fullview.viewer.scene import SceneData

log = logging.getLogger(__name__)

WEB = Path(__file__).resolve().parent / "web"
VENDOR = WEB / "node_modules"
VENDORED = ("three", "@photo-sphere-viewer")  # the only packages the page may load
MAX_BODY = 8 << 20  # bytes of a POSTed hand_points document
HAND_CHECK_FACTOR = 4.0  # a hand point farther than this many filter thresholds from its epipolar circle is flagged


class ViewerApp:
    """State shared by the request handlers: the scene data and a background rerun."""

    def __init__(self, pipeline: Pipeline, config: Config):
        self.pipeline, self.config = pipeline, config
        self.scene = SceneData(pipeline)
        self.rerun_thread: threading.Thread | None = None
        self.rerun_message = ""

    def rerun(self) -> str:
        """Rerun what the hand points changed (filter on), in the background under the workspace lock."""
        if self.rerun_thread is not None and self.rerun_thread.is_alive():
            return "a run is already going"

        def work():
            try:
                fresh = Pipeline(Dataset(self.pipeline.dataset.root), self.pipeline.ws, self.config)
                ran = fresh.run(wait=False)
                self.rerun_message = f"ran: {', '.join(ran) or 'nothing (all fresh)'}"
            except FullviewError as e:
                self.rerun_message = f"run failed: {e}"
            self.pipeline.dataset = Dataset(self.pipeline.dataset.root)
            self.scene = SceneData(Pipeline(self.pipeline.dataset, self.pipeline.ws, self.config))

        self.rerun_message = "running"
        self.rerun_thread = threading.Thread(target=work, daemon=True)
        self.rerun_thread.start()
        return "started"


def make_server(app: ViewerApp, port: int = 0) -> ThreadingHTTPServer:
    handler = type("Handler", (_Handler,), {"app": app})
    server = ThreadingHTTPServer(("127.0.0.1", port), handler)
    server.daemon_threads = True
    return server


class _Handler(BaseHTTPRequestHandler):
    app: ViewerApp
    server_version = "fullview-viewer"

    def log_message(self, fmt, *args):  # the default writes every request to stderr
        log.debug("%s " + fmt, self.address_string(), *args)

    # ---------------------------------------------------------------------------------------------- routing
    def do_GET(self):
        url = urlparse(self.path)
        query = {k: v[0] for k, v in parse_qs(url.query).items()}
        path = unquote(url.path)
        try:
            if path in ("/", "/index.html"):
                return self._file(WEB / "index.html")
            if path.startswith("/static/"):
                return self._file(_inside(WEB, path[len("/static/"):]))
            if path.startswith("/vendor/"):
                rel = path[len("/vendor/"):]
                if not rel.startswith(VENDORED):
                    return self._error(HTTPStatus.NOT_FOUND, "not a vendored package")
                return self._file(_inside(VENDOR, rel))
            if path == "/api/generation":  # polled every few seconds: cheap, no status computation
                return self._json({"generation": self.app.scene.generation(), "rerun": self.app.rerun_message})
            if path == "/api/state":
                state = self.app.scene.state()
                state["rerun"] = self.app.rerun_message
                return self._json(state)
            if path.startswith("/api/points/"):
                kind = path.rsplit("/", 1)[1]
                if kind not in ("sparse", "dense"):
                    return self._error(HTTPStatus.NOT_FOUND, "unknown cloud")
                return self._send(self.app.scene.points(kind), "application/octet-stream")
            if path == "/api/mesh":
                return self._send(self.app.scene.mesh(), "application/octet-stream")
            if path == "/api/matches":
                return self._json(self.app.scene.matches(query["a"], query["b"]))
            if path == "/api/hand_points":
                tracks = self.app.pipeline.dataset.hand_tracks()
                return self._json([{"name": t.name, "observations": t.observations} for t in tracks])
            if path.startswith("/pano/"):
                name = self._image(path[len("/pano/"):])
                return self._send(self.app.scene.panorama_jpeg(name, int(query.get("width", 2048))), "image/jpeg",
                                  cache=True)
            if path.startswith("/depth/"):
                png = self.app.scene.depth_png(self._image(path[len("/depth/"):]))
                return self._send(png, "image/png") if png else self._error(HTTPStatus.NOT_FOUND, "no depth map")
            return self._error(HTTPStatus.NOT_FOUND, "no such page")
        except (FullviewError, KeyError, ValueError) as e:
            return self._error(HTTPStatus.BAD_REQUEST, str(e))
        except BrokenPipeError:
            return None

    def do_POST(self):
        path = urlparse(self.path).path
        try:
            if path == "/api/hand_points":
                body = self._body()
                backup = self.app.pipeline.dataset.save_hand_points(body.get("points") if isinstance(body, dict)
                                                                    else None)
                return self._json({"saved": str(self.app.pipeline.dataset.hand_points_path),
                                   "backup": str(backup) if backup else None,
                                   "command": f"fullview run {self.app.pipeline.dataset.root}"
                                              f"{self.app.pipeline.ws.workspace_option(self.app.pipeline.dataset.root)}"})
            if path == "/api/hand_check":
                body = self._body()
                threshold = HAND_CHECK_FACTOR * self.app.config["filter"].threshold_deg
                return self._json({"threshold_deg": threshold, "pairs": self.app.scene.hand_check(
                    body.get("points") if isinstance(body, dict) else None, threshold)})
            if path == "/api/rerun":
                return self._json({"rerun": self.app.rerun()})
            return self._error(HTTPStatus.NOT_FOUND, "no such endpoint")
        except (FullviewError, ValueError) as e:
            return self._error(HTTPStatus.BAD_REQUEST, str(e))

    # ---------------------------------------------------------------------------------------------- helpers
    def _body(self):
        length = int(self.headers.get("Content-Length", 0))
        if length > MAX_BODY:
            raise ValueError("request too large")
        return json.loads(self.rfile.read(length) or b"null")

    def _image(self, name: str) -> str:
        if name not in self.app.pipeline.dataset.image_names:
            raise ValueError(f"unknown image {name!r}")
        return name

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
        return self._send(json.dumps({"error": message}).encode(), "application/json", status=status)

    def _send(self, data: bytes, kind: str, *, status: HTTPStatus = HTTPStatus.OK, cache: bool = False):
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
        self.end_headers()
        self.wfile.write(data)


def _inside(root: Path, rel: str) -> Path | None:
    """`root / rel` when it stays inside `root` (no '..' escapes), else None."""
    path = (root / rel).resolve()
    return path if path.is_relative_to(root.resolve()) else None
