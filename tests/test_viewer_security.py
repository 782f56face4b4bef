"""The viewer as a hostile web page, a hostile local client and a hostile file name would try it (issue 30): only its
own page drives it (token, Host, Origin, Content-Type, CSP), names stay text, only workspace files and listed images
are served, backups never overwrite each other, and every bad request gets a one-line answer, never a traceback."""

from __future__ import annotations

import contextlib
import http.client
import json
import logging
import os
import shlex
import shutil
import socket
import subprocess
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, quote, urlparse

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fullview.io import dataset as dataset_module
from fullview.io.config import load_config
from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace, image_stem
from fullview.stages.runner import Pipeline
from fullview.viewer.server import TOKEN_HEADER, VENDOR, ViewerApp, make_server, page_url
from tests.test_viewer import call, origin

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
EVIL = "<img src=x onerror=document.title='PWNED'+document.domain>.png"  # a legal file name (no '/')
EVIL_TRACK = "<img src=x onerror=document.title='PWNED_TRACK'>"
needs_page = pytest.mark.skipif(not (VENDOR / "three").is_dir(), reason="viewer/web/node_modules missing (make setup)")


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def evil(tiny_dataset, tmp_path_factory, tiny_set_args):
    """The tiny dataset with its second image named like HTML (and a hand track too), reconstructed through
    triangulation: cameras, a tour with hotspots, correlated views and hand points all show that name."""
    root = tmp_path_factory.mktemp("viewer_security")
    data = root / "evil"
    shutil.copytree(tiny_dataset, data, ignore=shutil.ignore_patterns("ground_truth"))
    (data / "images" / "pano_001.png").rename(data / "images" / EVIL)
    hand = yaml.safe_load((data / "hand_points.yaml").read_text())
    for point in hand["points"]:
        point["observations"] = {EVIL if k == "pano_001.png" else k: v for k, v in point["observations"].items()}
    hand["points"][0]["name"] = EVIL_TRACK
    (data / "hand_points.yaml").write_text(yaml.safe_dump(hand, sort_keys=False))
    config = load_config(None, [a for a in tiny_set_args if a != "--set"])
    dataset = Dataset(data)
    pipeline = Pipeline(dataset, Workspace(root / "ws", dataset.name), config)
    pipeline.run(until="triangulation")
    return pipeline, config


@pytest.fixture(scope="module")
def served(evil):
    """(app, printed URL) of a viewer over the evil dataset, in a thread."""
    with _serve(*evil) as running:
        yield running


@contextlib.contextmanager
def _serve(pipeline, config):
    app = ViewerApp(pipeline, config)
    httpd = make_server(app)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield app, page_url(httpd)
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.fixture(scope="module")
def copy_served(evil, tmp_path_factory):
    """A viewer over a private copy of the evil dataset and workspace (for tests that save or break files)."""
    pipeline, config = evil
    root = tmp_path_factory.mktemp("viewer_copy")
    shutil.copytree(pipeline.dataset.root, root / "evil")
    shutil.copytree(pipeline.ws.root, root / "ws" / "evil")
    dataset = Dataset(root / "evil")
    with _serve(Pipeline(dataset, Workspace(root / "ws", dataset.name), config), config) as running:
        yield running


@pytest.fixture(scope="module")
def server_log():
    """Every record the viewer's server logs (DEBUG and up: each request line with its status) while the module runs."""
    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.DEBUG)
    handler.emit = records.append
    logger = logging.getLogger("fullview.viewer")
    old_level = logger.level
    logger.setLevel(logging.DEBUG)
    logger.addHandler(handler)
    yield records
    logger.removeHandler(handler)
    logger.setLevel(old_level)


@pytest.fixture(scope="module")
def browser():
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (make setup)")
    if CHROMIUM is None:
        pytest.skip("Debian's chromium is not installed (make setup installs it)")
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--use-gl=swiftshader", "--enable-unsafe-swiftshader"])
        yield b
        b.close()


def _raw(url: str, method: str, path: str, body: bytes | None = None, headers: dict | None = None,
         *, token: bool = True) -> tuple[int, dict, bytes]:
    """One request as curl would send it (http.client: any Host, Origin, Content-Type, Content-Length)."""
    parsed = urlparse(url)
    conn = http.client.HTTPConnection(parsed.hostname, parsed.port, timeout=60)
    all_headers = {TOKEN_HEADER: parse_qs(parsed.query)["token"][0]} if token else {}
    all_headers |= headers or {}
    skip_host = any(k.lower() == "host" for k in all_headers)
    conn.putrequest(method, path, skip_host=skip_host, skip_accept_encoding=True)
    for k, v in all_headers.items():
        conn.putheader(k, v)
    if body is not None and not any(k.lower() == "content-length" for k in all_headers):
        conn.putheader("Content-Length", str(len(body)))
    conn.endheaders(body)
    answer = conn.getresponse()
    try:
        return answer.status, dict(answer.getheaders()), answer.read()
    finally:
        conn.close()


def _json_post(url: str, path: str, body: bytes, **extra) -> tuple[int, dict, bytes]:
    return _raw(url, "POST", path, body, {"Content-Type": "application/json", "Origin": origin(url).rstrip("/"),
                                          **extra})


def _one_line_error(status: int, data: bytes, expected: int = 400) -> str:
    assert status == expected, (status, data[:300])
    error = json.loads(data)["error"]
    assert error and "\n" not in error and "Traceback" not in error, error
    return error


def _no_errors_logged(records, since: int = 0):
    bad = [r for r in records[since:] if r.levelno >= logging.WARNING]
    assert not bad, [r.getMessage() for r in bad]


@contextlib.contextmanager
def _read_only(*folders: Path):
    """Make folders read-only for this process: chmod when not root; root ignores modes, so a read-only bind mount
    then (skipped where mounting is not allowed)."""
    if os.geteuid() != 0:
        modes = {}
        for folder in folders:
            for p in [folder, *folder.rglob("*")]:
                if p.is_dir() and not p.is_symlink():
                    modes[p] = p.stat().st_mode
                    p.chmod(modes[p] & ~0o222)
        try:
            yield
        finally:
            for p, mode in modes.items():
                p.chmod(mode)
        return
    mounted = []
    try:
        for folder in folders:
            if subprocess.run(["mount", "--bind", str(folder), str(folder)], capture_output=True).returncode:
                pytest.skip("running as root and cannot bind-mount: no way to make a folder read-only")
            mounted.append(folder)
            if subprocess.run(["mount", "-o", "remount,bind,ro", str(folder)], capture_output=True).returncode:
                pytest.skip("running as root and cannot remount read-only")
        yield
    finally:
        for folder in reversed(mounted):
            subprocess.run(["umount", str(folder)], check=True)


# ---------------------------------------------------------------------------------------- 1. cross-site requests
def test_curl_reproductions_are_refused(copy_served, server_log):
    """issue 30 item 1: Origin evil / Content-Type text/plain / no Origin / no or wrong token: 403, nothing saved."""
    app, url = copy_served
    path = app.pipeline.dataset.hand_points_path
    before = path.read_bytes()
    start = len(server_log)
    body = b'{"points":[]}'
    own = origin(url).rstrip("/")
    attempts = {
        "evil origin, text/plain": {"Origin": "http://evil.example", "Content-Type": "text/plain"},
        "evil origin, json": {"Origin": "http://evil.example", "Content-Type": "application/json"},
        "own origin, text/plain": {"Origin": own, "Content-Type": "text/plain"},
        "own origin, form": {"Origin": own, "Content-Type": "application/x-www-form-urlencoded"},
        "no origin, json": {"Content-Type": "application/json"},
        "null origin": {"Origin": "null", "Content-Type": "application/json"},
        "other port": {"Origin": "http://127.0.0.1:1", "Content-Type": "application/json"},
    }
    for what, headers in attempts.items():
        for endpoint in ("/api/hand_points", "/api/rerun", "/api/hand_check"):
            status, _, data = _raw(url, "POST", endpoint, body, headers)
            _one_line_error(status, data, 403)
    good = {"Origin": own, "Content-Type": "application/json"}
    for token_headers in ({TOKEN_HEADER: "wrong"}, {TOKEN_HEADER: ""}, {TOKEN_HEADER: "é" * 43}):
        status, _, data = _raw(url, "POST", "/api/hand_points", body, good | token_headers)
        assert "token" in _one_line_error(status, data, 403)
    status, _, data = _raw(url, "POST", "/api/hand_points", body, good, token=False)  # no token at all
    _one_line_error(status, data, 403)
    token = parse_qs(urlparse(url).query)["token"][0]
    status, _, data = _raw(url, "POST", f"/api/hand_points?token={token}", body, good, token=False)
    _one_line_error(status, data, 403)  # a POST must send the header: a query token is only for <img> URLs
    assert path.read_bytes() == before and app.rerun_thread is None
    _no_errors_logged(server_log, start)
    # the same request with everything right is what the page sends, and it is served
    status, _, data = _json_post(url, "/api/hand_check", b'{"points":[]}')
    assert status == 200 and json.loads(data)["pairs"] == []


def test_the_token_guards_every_read_of_data(served):
    """issue 30 item 1: GETs of workspace or dataset data need the token (header or ?token=); the page shell does
    not, and it holds no data."""
    app, url = served
    name = quote(app.pipeline.dataset.image_names[0])
    data_paths = ["/api/state", "/api/generation", "/api/hand_points", "/api/points/sparse", "/api/mesh",
                  f"/pano/{name}?width=256", f"/depth/{name}", f"/api/matches?a={name}&b={name}"]
    for path in data_paths:
        status, _, data = _raw(url, "GET", path, token=False)
        _one_line_error(status, data, 403)
        sep = "&" if "?" in path else "?"
        status, _, data = _raw(url, "GET", f"{path}{sep}token=nope", token=False)
        _one_line_error(status, data, 403)
    token = parse_qs(urlparse(url).query)["token"][0]
    for path in ("/api/state", f"/pano/{name}?width=256"):
        assert _raw(url, "GET", path)[0] == 200  # header
        sep = "&" if "?" in path else "?"
        assert _raw(url, "GET", f"{path}{sep}token={token}", token=False)[0] == 200  # query (<img> URLs)
    for shell in ("/", "/index.html", "/static/app.js", "/vendor/three/build/three.module.js"):
        status, _, data = _raw(url, "GET", shell, token=False)
        assert status == 200 and token.encode() not in data
        assert b"onerror=document.title" not in data  # neither the image names nor the hand tracks


def test_the_token_is_new_at_every_server_start(evil):
    pipeline, config = evil
    tokens = {ViewerApp(pipeline, config).token for _ in range(5)}
    assert len(tokens) == 5 and all(len(t) >= 43 for t in tokens)  # 32 random bytes, URL-safe base64


@needs_page
def test_a_page_of_another_origin_cannot_save_rerun_or_read(copy_served, browser, server_log):
    """issue 30 item 1, in Chromium: a page served from another 127.0.0.1 port sends no-cors POSTs (fetch and a
    text/plain form) to /api/hand_points and /api/rerun and loads /api/... and /pano/... as images; they reach the
    server and are refused: hand_points.yaml unchanged, no backup written, no run started, no image loaded."""
    app, url = copy_served
    path = app.pipeline.dataset.hand_points_path
    before = path.read_bytes()
    backups_before = sorted(path.parent.glob("hand_points.yaml.*"))
    target = origin(url).rstrip("/")
    name = quote(app.pipeline.dataset.image_names[0])
    evil_page = f"""<!doctype html><html><body>
<iframe name="sink"></iframe>
<form id="f" method="POST" action="{target}/api/hand_points" enctype="text/plain" target="sink">
<input name='{{"points":[], "x":"' value='"}}'></form>
<script>
const results = {{}};
const load = (src) => new Promise((done) => {{ const i = new Image(); i.onload = () => done('loaded');
  i.onerror = () => done('refused'); i.src = src; }});
(async () => {{
  for (const p of ['/api/hand_points', '/api/rerun']) {{
    for (const ct of [undefined, 'text/plain', 'application/x-www-form-urlencoded']) {{
      const init = {{ mode: 'no-cors', method: 'POST', body: '{{"points":[]}}' }};
      if (ct) init.headers = {{ 'Content-Type': ct }};
      try {{ await fetch('{target}' + p, init); results[p + ' ' + ct] = 'sent'; }}
      catch (e) {{ results[p + ' ' + ct] = String(e); }}
    }}
  }}
  results.img_api = await load('{target}/api/hand_points');
  results.img_pano = await load('{target}/pano/{name}?width=256');
  document.getElementById('f').submit();
  await new Promise((r) => setTimeout(r, 500));
  window.done = results;
}})();
</script></body></html>""".encode()

    class Evil(BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(evil_page)))
            self.end_headers()
            self.wfile.write(evil_page)

        def log_message(self, *args):
            pass

    other = ThreadingHTTPServer(("127.0.0.1", 0), Evil)
    threading.Thread(target=other.serve_forever, daemon=True).start()
    start = len(server_log)
    page = browser.new_page()
    try:
        page.goto(f"http://127.0.0.1:{other.server_address[1]}/")
        page.wait_for_function("() => window.done", timeout=30000)
        results = page.evaluate("window.done")
    finally:
        page.close()
        other.shutdown()
        other.server_close()
    assert results["img_api"] == "refused" and results["img_pano"] == "refused", results
    answered = [r.getMessage() for r in server_log[start:] if "POST /api/" in r.getMessage()]
    assert sum("/api/hand_points" in m for m in answered) >= 4 and sum("/api/rerun" in m for m in answered) >= 3
    assert all('" 403 ' in m for m in answered), answered  # they reached the server, which refused every one
    assert path.read_bytes() == before and sorted(path.parent.glob("hand_points.yaml.*")) == backups_before
    assert app.rerun_thread is None and app.rerun_message == ""


def test_every_answer_carries_a_strict_csp_and_no_referrer(served):
    """issue 30 item 1: the page may run only its own scripts (and its hashed import map), load only from itself,
    and never be framed; no answer may be sniffed into another type or leak the token in a Referer."""
    app, url = served
    for path, token in (("/", False), ("/static/app.js", False), ("/api/state", True), ("/api/nothing", True),
                        ("/api/state", False)):
        _, headers, _ = _raw(url, "GET", path, token=token)
        csp = {d.split()[0]: d.split()[1:] for d in headers["Content-Security-Policy"].split("; ")}
        assert csp["default-src"] == ["'self'"] and csp["connect-src"] == ["'self'"]
        assert csp["frame-ancestors"] == ["'none'"] and csp["object-src"] == ["'none'"]
        script = csp["script-src"]
        assert script[0] == "'self'" and len(script) == 2 and script[1].startswith("'sha256-"), script
        assert not any("unsafe" in v for vs in csp.values() for v in vs)
        assert headers["X-Content-Type-Options"] == "nosniff" and headers["Referrer-Policy"] == "no-referrer"


@needs_page
def test_the_csp_stops_a_script_injected_into_the_page(served, browser):
    """issue 30 item 1: even a script element that got into the page (the XSS the CSP is the second wall against)
    does not run, while the page itself runs without a single CSP complaint."""
    app, url = served
    page = browser.new_page()
    problems = []
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    try:
        page.goto(url)
        page.wait_for_function("() => window.fullview && window.fullview.ready", timeout=60000)
        assert not problems, problems
        page.evaluate("""() => { const s = document.createElement('script');
            s.textContent = "document.title = 'INJECTED'"; document.body.appendChild(s); }""")
        page.wait_for_timeout(300)
        assert page.title() != "INJECTED"
        assert any("Content Security Policy" in p for p in problems), problems
    finally:
        page.close()


# ------------------------------------------------------------------------------------------------ 3. DNS rebinding
def test_a_foreign_host_header_is_refused(served):
    """issue 30 item 3: `curl -H 'Host: attacker.example:PORT'` (a rebound DNS name) gets 421 for every path."""
    app, url = served
    port = urlparse(url).port
    name = quote(app.pipeline.dataset.image_names[0])
    for host in (f"attacker.example:{port}", "attacker.example", f"127.0.0.1:{port + 1}", f"127.0.0.1.evil:{port}",
                 f"localhost.attacker.example:{port}", ""):
        for path in ("/api/hand_points", f"/pano/{name}", "/api/points/dense", "/api/points/sparse", "/",
                     "/static/app.js"):
            status, _, data = _raw(url, "GET", path, headers={"Host": host})
            _one_line_error(status, data, 421)
        status, _, data = _json_post(url, "/api/hand_points", b'{"points":[]}', Host=host)
        _one_line_error(status, data, 421)
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"LOCALHOST:{port}", f"[::1]:{port}"):
        assert _raw(url, "GET", "/api/generation", headers={"Host": host})[0] == 200


# ------------------------------------------------------------------------------------------------ 4. names as text
@needs_page
def test_an_image_named_like_html_stays_text(served, browser):
    """issue 30 item 4: an image named `<img src=x onerror=...>.png` (and a hand track named likewise) shows as that
    text in the correlated views' list, the tour's caption, hotspots and tooltips, and the track list; nothing runs."""
    app, url = served
    page = browser.new_page(viewport={"width": 1600, "height": 1000})
    problems = []
    page.on("pageerror", lambda e: problems.append(str(e)))
    try:
        page.goto(url)
        page.wait_for_function("() => window.fullview && window.fullview.ready", timeout=60000)
        assert EVIL in page.inner_text("#corr-pick-list")
        x, y = page.evaluate("(n) => window.fullview.cameraScreenPosition(n)", EVIL)
        page.mouse.click(x, y)
        page.wait_for_function("(n) => window.fullview.tour && window.fullview.tour.ready && "
                               "window.fullview.tour.name === n", arg=EVIL, timeout=30000)
        assert EVIL in page.inner_text(".psv-caption-content")
        other = "pano_000.png"
        page.evaluate("(n) => window.fullview.moveTo(n)", other)  # its hotspots lead back to the evil name
        page.wait_for_function("(n) => window.fullview.tour.ready && window.fullview.tour.name === n", arg=other,
                               timeout=30000)
        hotspot = page.locator(".hotspot", has_text=EVIL)
        assert hotspot.count() == 1
        (target,) = [n for n in page.evaluate("() => window.fullview.tour.neighbours") if n["name"] == EVIL]
        page.evaluate("(p) => window.fullview.tourLookAt(p)", {"yaw": target["yaw"], "pitch": target["pitch"]})
        page.wait_for_timeout(300)
        hotspot.hover()  # the tooltip (HTML in Photo Sphere Viewer) shows the name as text
        page.wait_for_selector(".psv-tooltip", timeout=10000)
        assert EVIL in page.inner_text(".psv-tooltip")
        page.click("button[data-tab=corr]")
        page.check("#pick-mode")
        assert page.locator("#tracks input").first.input_value() == EVIL_TRACK
        page.wait_for_timeout(500)
        assert "PWNED" not in page.title()
        assert page.evaluate("() => document.querySelectorAll('[onerror], img[src=\"x\"]').length") == 0
        assert not problems, problems
    finally:
        page.close()


# ------------------------------------------------------------------------------------------------ 8. what is served
def test_a_symlink_out_of_the_workspace_is_not_served(copy_served):
    """issue 30 item 8: `ln -sf /etc/passwd WS/ds/densify/depth/pano_000.png` (and a planted panorama cache
    entry) are refused; the real depth map beside it still is served."""
    app, url = copy_served
    ws = app.pipeline.ws
    name = "pano_000.png"
    depth = ws.path("depth_image", stem=image_stem(name))
    depth.parent.mkdir(parents=True, exist_ok=True)
    secret = depth.parent.parent.parent.parent / "secret.txt"  # outside the dataset's workspace folder
    secret.write_text("root:x:0:0:root:/root:/bin/bash\n")
    for target in ("/etc/passwd", str(secret)):
        depth.unlink(missing_ok=True)
        depth.symlink_to(target)
        status, _, data = _raw(url, "GET", f"/depth/{quote(name)}")
        assert b"root:" not in data
        assert "not served" in _one_line_error(status, data, 403)
    depth.unlink()
    depth.mkdir()  # a folder named like the file
    status, _, data = _raw(url, "GET", f"/depth/{quote(name)}")
    _one_line_error(status, data, 403)
    depth.rmdir()
    real = depth.with_name("real.png")
    real.write_bytes(b"\x89PNG inside the workspace")
    depth.symlink_to(real)  # a link that stays inside the workspace is fine
    status, _, data = _raw(url, "GET", f"/depth/{quote(name)}")
    assert status == 200 and data == real.read_bytes()
    # a cache entry of the panorama the viewer would read back as it is
    status, _, _ = _raw(url, "GET", f"/pano/{quote(name)}?width=256")
    cached = next(ws.root.glob("view_cache/pano_000_256_*.jpg"))
    cached.unlink()
    cached.symlink_to(secret)
    status, _, data = _raw(url, "GET", f"/pano/{quote(name)}?width=256")
    assert b"root:" not in data
    _one_line_error(status, data, 403)


def test_only_listed_images_are_served(served):
    """issue 30 item 8: /pano/ and /depth/ take a name from the dataset's image list, nothing else."""
    app, url = served
    for name in ("../hand_points.yaml", "..%2fhand_points.yaml", "%2e%2e/%2e%2e/etc/passwd", "/etc/passwd",
                 "missing.png", "pano_000.PNG"):
        for route in ("pano", "depth"):
            status, _, data = _raw(url, "GET", f"/{route}/{name}")
            assert status in (403, 404) and b"observations" not in data and b"root:" not in data, (route, name, status)


def test_an_image_linked_into_images_is_still_served(evil, tmp_path):
    """issue 30 item 8: a symlink the user placed in images/ is part of the image list, so it is served."""
    pipeline, config = evil
    data = tmp_path / "linked"
    shutil.copytree(pipeline.dataset.root, data)
    elsewhere = tmp_path / "elsewhere.png"
    (data / "images" / "pano_002.png").rename(elsewhere)
    (data / "images" / "pano_002.png").symlink_to(elsewhere)
    dataset = Dataset(data)
    with _serve(Pipeline(dataset, Workspace(tmp_path / "ws", dataset.name), config), config) as (_, url):
        status, headers, body = _raw(url, "GET", "/pano/pano_002.png?width=256")
    assert status == 200 and headers["Content-Type"] == "image/jpeg" and body[:2] == b"\xff\xd8"


# ------------------------------------------------------------------------------------------------ 2. backups
def _points(app) -> list[dict]:
    return [{"name": t.name, "observations": {k: list(v) for k, v in t.observations.items()}}
            for t in app.pipeline.dataset.hand_tracks()]


def test_twenty_concurrent_saves_keep_the_original(copy_served, server_log):
    """issue 30 item 2: 20 saves at once through the real server, each a different file: the original (every
    track) is kept in hand_points.yaml.orig.bak and in a timestamped backup; no two backups share a name and every
    file that was replaced is in some backup."""
    app, url = copy_served
    path = app.pipeline.dataset.hand_points_path
    original = path.read_bytes()
    n_original = len(app.pipeline.dataset.hand_tracks())
    points = _points(app)
    start = len(server_log)
    barrier = threading.Barrier(20)
    answers = [None] * 20

    def save(k):
        mine = [dict(p, name=f"save{k}_{p['name']}") for p in points[:-1 - k % 5]]
        barrier.wait()
        answers[k] = call(url, "api/hand_points", {"points": mine})

    threads = [threading.Thread(target=save, args=(k,)) for k in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(a and a["backup"] for a in answers)
    assert len({a["backup"] for a in answers}) == 20  # twenty distinct files, none overwritten
    backups = {p: p.read_bytes() for p in path.parent.glob("hand_points.yaml.*.bak")}
    assert (path.parent / "hand_points.yaml.orig.bak").read_bytes() == original
    assert any(b == original for p, b in backups.items() if not p.name.endswith(".orig.bak"))
    assert len(yaml.safe_load(original)["points"]) == n_original
    written = {a["backup"] for a in answers}
    assert all(Path(b).exists() for b in written)
    # every version a save replaced is kept: the original and 19 of the 20 saved files (the last is current)
    contents = {backups[Path(b)] for b in written}
    assert len(contents) == 20 and path.read_bytes() not in contents
    _no_errors_logged(server_log, start)
    path.write_bytes(original)


def test_two_saves_in_one_second_keep_both_previous_files(evil, tmp_path):
    """issue 30 item 2: a double click (two saves within a microsecond of each other, same second) leaves two
    backups, the first holding the original."""
    data = tmp_path / "ds"
    shutil.copytree(evil[0].dataset.root, data)
    dataset = Dataset(data)
    original = dataset.hand_points_path.read_bytes()
    tracks = [{"name": t.name, "observations": {k: list(v) for k, v in t.observations.items()}}
              for t in dataset.hand_tracks()]
    first = dataset.save_hand_points(tracks[:-1])
    second = dataset.save_hand_points(tracks[:-2])
    assert first != second and first.read_bytes() == original
    assert len(yaml.safe_load(second.read_text())["points"]) == len(tracks) - 1


def test_only_the_newest_backups_are_kept_but_never_the_original(evil, tmp_path, monkeypatch):
    """issue 30 item 2: BACKUPS_KEPT timestamped backups stay (the newest), plus the original, whatever the count."""
    monkeypatch.setattr(dataset_module, "BACKUPS_KEPT", 3)
    data = tmp_path / "ds"
    shutil.copytree(evil[0].dataset.root, data)
    dataset = Dataset(data)
    original = dataset.hand_points_path.read_bytes()
    tracks = [{"name": t.name, "observations": {k: list(v) for k, v in t.observations.items()}}
              for t in dataset.hand_tracks()]
    made = [dataset.save_hand_points(tracks[:len(tracks) - 1 - k]) for k in range(7)]
    stamped = sorted(p for p in data.glob("hand_points.yaml.2*.bak"))
    assert stamped == sorted(made[-3:])
    assert (data / "hand_points.yaml.orig.bak").read_bytes() == original
    assert not list(data.glob(".hand_points.yaml*"))  # no temporary file left behind


# ------------------------------------------------------------------------------------------------ 11. robustness
BAD_BODIES = {
    "100k nested [": b"[" * 100_000,
    "100k nested {": b'{"a":' * 100_000,
    "points are numbers": b'{"points":[1,2]}',
    "observations a list": b'{"points":[{"name":"a","observations":[1]}]}',
    "observations only": b'{"observations":[1]}',
    "NaN": b'{"points":[{"name":"a","observations":{"pano_000.png":[NaN,1],"pano_002.png":[1,1]}}]}',
    "Infinity": b'{"points":[{"name":"a","observations":{"pano_000.png":[Infinity,1],"pano_002.png":[1,1]}}]}',
    "1e400": b'{"points":[{"name":"a","observations":{"pano_000.png":[1e400,1],"pano_002.png":[1,1]}}]}',
    "huge integer": b'{"points":[{"name":"a","observations":{"pano_000.png":[' + b"9" * 400 + b',1]}}]}',
    "5000-digit integer": b'{"points":[' + b"9" * 5000 + b"]}",
    "not UTF-8": b'{"points":["\xff\xfe"]}',
    "not JSON": b"points: []",
    "empty": b"",
    "a string": b'"points"',
    "points a mapping": b'{"points":{"a":1}}',
    "name a list": b'{"points":[{"name":[1],"observations":{}}]}',
    "unknown image": b'{"points":[{"name":"a","observations":{"../x.png":[1,1],"pano_000.png":[1,1]}}]}',
    "pixel of three": b'{"points":[{"name":"a","observations":{"pano_000.png":[1,1,1],"pano_002.png":[1,1]}}]}',
    "pixel outside": b'{"points":[{"name":"a","observations":{"pano_000.png":[-1,1],"pano_002.png":[1,1]}}]}',
    "bool pixel": b'{"points":[{"name":"a","observations":{"pano_000.png":[true,1],"pano_002.png":[1,1]}}]}',
}


@pytest.mark.parametrize("what", BAD_BODIES)
@pytest.mark.parametrize("endpoint", ["/api/hand_points", "/api/hand_check"])
def test_bad_bodies_get_a_one_line_400(copy_served, server_log, endpoint, what):
    """issue 30 items 11 and 13: deep nesting (RecursionError), points that are not objects, NaN ("Eigenvalues did
    not converge"), overflowing numbers... each a 400 with one line, no traceback, hand_points.yaml unchanged."""
    app, url = copy_served
    path = app.pipeline.dataset.hand_points_path
    before = path.read_bytes()
    start = len(server_log)
    status, _, data = _json_post(url, endpoint, BAD_BODIES[what])
    _one_line_error(status, data)
    assert path.read_bytes() == before
    _no_errors_logged(server_log, start)


def test_hand_check_names_what_is_wrong(served):
    """issue 30 item 13: NaN and a point that is not an object are named, not 'Eigenvalues did not converge'."""
    _, url = served
    status, _, data = _json_post(url, "/api/hand_check", BAD_BODIES["NaN"])
    assert "NaN" in _one_line_error(status, data)
    status, _, data = _json_post(url, "/api/hand_check", b'{"points":[1,2]}')
    assert "points[0]" in _one_line_error(status, data)


def test_matches_without_b_says_which_parameter_is_missing(served):
    """issue 30 item 13: `/api/matches?a=...` answered `"'b'"`; now it names the missing parameter."""
    app, url = served
    a = quote(app.pipeline.dataset.image_names[0])
    status, _, data = _raw(url, "GET", f"/api/matches?a={a}")
    assert _one_line_error(status, data) == "missing query parameter 'b'"
    status, _, data = _raw(url, "GET", f"/api/matches?a={a}&b=nope.png")
    assert "nope.png" in _one_line_error(status, data, 404)
    status, _, data = _raw(url, "GET", f"/pano/{a}?width=-5")
    assert "width" in _one_line_error(status, data)


@pytest.mark.parametrize("length", ["-1", "-99999999", str(1 << 40), "12abc", "+5", "1_0", ""])
def test_a_bad_content_length_is_refused_before_reading(copy_served, server_log, length):
    """issue 30 item 13: a negative Content-Length held a request thread (read(-1) waits for the end of input); a
    huge or malformed one is refused from the headers alone: the answer comes while the client sends nothing more."""
    app, url = copy_served
    parsed = urlparse(url)
    token = parse_qs(parsed.query)["token"][0]
    start = len(server_log)
    with socket.create_connection((parsed.hostname, parsed.port), timeout=60) as s:
        s.sendall((f"POST /api/hand_points HTTP/1.1\r\nHost: {parsed.netloc}\r\nOrigin: {origin(url).rstrip('/')}\r\n"
                   f"Content-Type: application/json\r\n{TOKEN_HEADER}: {token}\r\nContent-Length: {length}\r\n\r\n")
                  .encode())
        answer = s.makefile("rb").read()  # the server answers and closes without waiting for a body
    head, _, body = answer.partition(b"\r\n\r\n")
    status = int(head.split()[1])
    assert status in (400, 413), head
    _one_line_error(status, body, status)
    _no_errors_logged(server_log, start)


def test_a_save_to_a_read_only_dataset_names_the_file(evil, tmp_path, server_log):
    """issue 30 item 11: saving into a read-only dataset answers 400 naming hand_points.yaml (was a traceback)."""
    pipeline, config = evil
    data = tmp_path / "ro"
    shutil.copytree(pipeline.dataset.root, data)
    dataset = Dataset(data)
    before = dataset.hand_points_path.read_bytes()
    with _serve(Pipeline(dataset, Workspace(tmp_path / "ws", dataset.name), config), config) as (app, url):
        points = _points(app)
        start = len(server_log)
        with _read_only(data):
            status, _, body = _json_post(url, "/api/hand_points", json.dumps({"points": points[:-1]}).encode())
    error = _one_line_error(status, body)
    assert str(dataset.hand_points_path) in error and ("read-only" in error.lower() or "permission" in error.lower())
    assert dataset.hand_points_path.read_bytes() == before
    _no_errors_logged(server_log, start)


def test_a_rerun_on_a_read_only_workspace_reports_its_failure(evil, tmp_path):
    """issue 30 item 11: the rerun thread's OSError left /api/generation "running" forever; now the run ends with
    "run failed: ..." naming the path."""
    pipeline, config = evil
    data = tmp_path / "ds"
    shutil.copytree(pipeline.dataset.root, data)
    shutil.copytree(pipeline.ws.root, tmp_path / "ws" / "ds")
    dataset = Dataset(data)
    with _serve(Pipeline(dataset, Workspace(tmp_path / "ws", dataset.name), config), config) as (app, url):
        with _read_only(tmp_path / "ws"):
            assert call(url, "api/rerun", {}) == {"rerun": "started"}
            app.rerun_thread.join(timeout=300)
            assert not app.rerun_thread.is_alive()
            message = call(url, "api/generation")["rerun"]
    assert message.startswith("run failed: ") and str(tmp_path / "ws") in message, message


def test_the_rerun_command_is_shell_quoted(evil, tmp_path):
    """issue 30 item 13: a dataset path with spaces and quotes gives a command a shell reads back as the same
    arguments."""
    pipeline, config = evil
    data = tmp_path / "my data's; rm -rf ~" / "evil"
    shutil.copytree(pipeline.dataset.root, data)
    dataset = Dataset(data)
    app = ViewerApp(Pipeline(dataset, Workspace(tmp_path / "ws $HOME", dataset.name), config), config)
    assert shlex.split(app.rerun_command()) == ["fullview", "run", str(data), "-w", str(tmp_path / "ws $HOME")]


def _view(dataset: Path, ws: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fullview", "view", str(dataset), "-w", str(ws), "--no-browser",
                           *args], capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("port", ["70000", "-1", "65536"])
def test_view_with_a_port_out_of_range_is_one_line(evil, port):
    """issue 30 item 11: `view --port 70000` was an OverflowError."""
    pipeline, _ = evil
    done = _view(pipeline.dataset.root, pipeline.ws.root.parent, "--port", port)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and f"--port {port}" in lines[0] and "65535" in lines[0], done.stderr


def test_view_on_a_busy_port_is_one_line(evil):
    """issue 30 item 11: a port in use says so and how to pick another, exit code 2."""
    pipeline, _ = evil
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        done = _view(pipeline.dataset.root, pipeline.ws.root.parent, "--port", str(port))
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [f"fullview: error: port {port} is in use; pick another with --port"]


# ------------------------------------------------------------------------------------------------ property tests
def _json_values():
    scalars = st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20)
    return st.recursive(scalars, lambda children: st.lists(children, max_size=5)
                        | st.dictionaries(st.text(max_size=10), children, max_size=5), max_leaves=30)


def _near_valid_bodies(names: list[str]):
    """Bodies shaped like the page's: points with names and observations, with wrong bits mixed in."""
    number = (st.floats(allow_nan=False) | st.integers(-10, 600) | st.floats(0, 512) | st.booleans()
              | st.text(max_size=3))
    pixel = st.lists(number, min_size=0, max_size=3) | number
    image = st.sampled_from(names) | st.text(max_size=12)
    point = st.fixed_dictionaries({"observations": st.dictionaries(image, pixel, max_size=4)},
                                  optional={"name": st.text(max_size=12) | st.integers(), "extra": st.integers()})
    return st.fixed_dictionaries({"points": st.lists(point | _json_values(), max_size=12)})


def _property_check(app, url, server_log, endpoint: str, body) -> None:
    path = app.pipeline.dataset.hand_points_path
    before = path.read_bytes()
    start = len(server_log)
    data = json.dumps(body).encode()  # json.dumps writes NaN/Infinity for inf floats: a strict server refuses them
    status, _, answer = _json_post(url, endpoint, data)
    assert status in (200, 400), (status, answer[:300])
    parsed = json.loads(answer)
    if status == 400:
        _one_line_error(status, answer)
        assert path.read_bytes() == before
    elif endpoint == "/api/hand_points":
        saved = Dataset(app.pipeline.dataset.root).hand_tracks()
        assert [t.name for t in saved] == [t.name for t in Dataset(app.pipeline.dataset.root)._parse_hand_points(
            path, body)]
        path.write_bytes(before)
    else:
        assert isinstance(parsed["pairs"], list)
    _no_errors_logged(server_log, start)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                  HealthCheck.too_slow])
@given(data=st.data())
def test_any_json_body_is_answered_never_crashed(copy_served, server_log, data):
    """Property (issue 30): POST /api/hand_points and /api/hand_check with arbitrary JSON, or JSON shaped like the
    page's with wrong bits: 200 or a one-line 400, never a 500 or a traceback in the log; on a 400 the file is
    unchanged, on a 200 it holds exactly the validated tracks."""
    app, url = copy_served
    names = app.pipeline.dataset.image_names
    body = data.draw(_json_values() | _near_valid_bodies(names) | st.fixed_dictionaries({"points": _json_values()}))
    endpoint = data.draw(st.sampled_from(["/api/hand_points", "/api/hand_check"]))
    _property_check(app, url, server_log, endpoint, body)
