"""`fullview view`: serve the viewer page for one dataset on 127.0.0.1 until Ctrl-C."""

from __future__ import annotations

import errno
import logging
import webbrowser

from fullview.io.config import Config, ConfigError
from fullview.stages.runner import Pipeline
from fullview.viewer.server import VENDOR, VENDORED, ViewerApp, make_server, page_url

log = logging.getLogger(__name__)

PORTS = range(0, 65536)  # TCP ports; 0 lets the system pick a free one


def check_port(port: int) -> None:
    if port not in PORTS:
        raise ConfigError(f"--port {port}: a port is 0 (any free one) to 65535")


def view(pipeline: Pipeline, config: Config, *, port: int = 0, open_browser: bool = True, note: str = "") -> None:
    """Serve until Ctrl-C; `note` (the results' freshness) is logged once the port is bound, so a refused start is
    one line."""
    check_port(port)
    missing = [p for p in VENDORED if not (VENDOR / p).is_dir()]
    if missing:
        raise ConfigError(f"{VENDOR}: the viewer's JavaScript libraries are missing ({', '.join(missing)}); "
                          "run `make setup` (npm ci in viewer/web)")
    app = ViewerApp(pipeline, config)
    try:
        server = make_server(app, port)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise ConfigError(f"port {port} is in use; pick another with --port") from None
        if e.errno == errno.EACCES:
            raise ConfigError(f"port {port} needs privileges on this system; pick another with --port") from None
        raise
    if note:
        log.info("%s", note)
    # The token in the URL is what lets only this page drive the server: print it, do not log it elsewhere.
    url = page_url(server)
    print(f"fullview viewer of {pipeline.dataset.name}: {url}  (Ctrl-C stops it)", flush=True)
    if open_browser:
        try:
            webbrowser.open(url)
        except webbrowser.Error:
            log.info("no browser to open; visit the URL above")
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
