"""`fullview view`: serve the viewer page for one dataset on 127.0.0.1 until Ctrl-C."""

from __future__ import annotations

import logging
import webbrowser

from fullview.io.config import Config, ConfigError
from fullview.stages.runner import Pipeline
from fullview.viewer.server import VENDOR, VENDORED, ViewerApp, make_server

log = logging.getLogger(__name__)


def view(pipeline: Pipeline, config: Config, *, port: int = 0, open_browser: bool = True) -> None:
    missing = [p for p in VENDORED if not (VENDOR / p).is_dir()]
    if missing:
        raise ConfigError(f"{VENDOR}: the viewer's JavaScript libraries are missing ({', '.join(missing)}); "
                          "run `make setup` (npm ci in viewer/web)")
    server = make_server(ViewerApp(pipeline, config), port)
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    print(f"fullview viewer of {pipeline.dataset.name}: {url}  (Ctrl-C stops it)", flush=True)
    if open_browser:
        try:
            webbrowser.open(url)
        except webbrowser.Error:
            log.info("no browser to open; visit %s", url)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
