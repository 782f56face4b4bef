"""The viewer in a real headless browser (Debian's chromium through Playwright): loads offline and cleanly, the 3-D
scene is drawn, cameras open the tour, hotspots walk to the right neighbour keeping the view direction, clicks in the
correlated views put epipolar circles and markers where Python's geometry puts them, and the hand-point picker
writes hand_points.yaml atomically."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np
import pytest
import yaml

from fullview.io.config import load_config
from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace
from fullview.sfm.camera import bearings_to_lonlat, bearings_to_pixels, pixels_to_bearings
from fullview.stages.runner import Pipeline
from fullview.viewer.server import TOKEN_HEADER, VENDOR, ViewerApp, make_server, page_url

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (make setup)")
pytestmark = [
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (make setup installs it)"),
    pytest.mark.skipif(not (VENDOR / "three").is_dir(), reason="viewer/web/node_modules missing (make setup)"),
]
SETTINGS = ["densify.working_width=512", "densify.rect_height=256", "densify.min_pair_inliers=30"]
VIEWPORT = {"width": 1600, "height": 1000}


@pytest.fixture(scope="module")
def reconstructed(tiny_dataset, tmp_path_factory, tiny_set_args):
    root = tmp_path_factory.mktemp("viewer")
    dataset_dir = root / "tiny"
    shutil.copytree(tiny_dataset, dataset_dir)  # the picker writes hand_points.yaml
    config = load_config(None, [a for a in tiny_set_args if a != "--set"] + SETTINGS)
    dataset = Dataset(dataset_dir)
    pipeline = Pipeline(dataset, Workspace(root / "ws", dataset.name), config)
    pipeline.run()
    return pipeline, config


@pytest.fixture(scope="module")
def server(reconstructed):
    pipeline, config = reconstructed
    httpd = make_server(ViewerApp(pipeline, config))
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield page_url(httpd)
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture(scope="module")
def browser():
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--use-gl=swiftshader", "--enable-unsafe-swiftshader"])
        yield b
        b.close()


@pytest.fixture
def page(browser, server):
    page = browser.new_page(viewport=VIEWPORT)
    page.problems, page.requests = [], []
    page.on("console", lambda m: page.problems.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: page.problems.append(str(e)))
    page.on("request", lambda r: page.requests.append(r.url))
    page.goto(server)
    page.wait_for_function("() => window.fullview && window.fullview.ready", timeout=30000)
    yield page
    page.close()


def origin(url: str) -> str:
    """http://127.0.0.1:PORT/ of a page URL `fullview view` printed (http://127.0.0.1:PORT/?token=...)."""
    return f"http://{urlparse(url).netloc}/"


def call(url: str, path: str, body=None, *, timeout: float = 60):
    """What the viewer's own page sends: GET or (with a body) POST of JSON to `path`, with the token of the printed
    `url`, the server's own Origin and Content-Type: application/json. Returns the parsed JSON answer."""
    headers = {TOKEN_HEADER: parse_qs(urlparse(url).query)["token"][0]}
    if body is not None:
        headers |= {"Content-Type": "application/json", "Origin": origin(url).rstrip("/")}
    request = urllib.request.Request(origin(url) + path, data=None if body is None else json.dumps(body).encode(),
                                     method="GET" if body is None else "POST", headers=headers)
    with urllib.request.urlopen(request, timeout=timeout) as answer:
        return json.loads(answer.read())


def _poses(pipeline):
    sparse = pipeline.ws.load_sparse()
    names = [str(n) for n in sparse["image_names"]]
    return names, sparse


# ------------------------------------------------------------------------------------------------ loading
def test_loads_offline_without_console_errors(page, server):
    time.sleep(0.5)
    assert not page.problems, page.problems
    outside = [u for u in page.requests if not (u.startswith(origin(server)) or u.startswith(("blob:", "data:")))]
    assert not outside, outside
    assert "fullview · tiny" in page.inner_text("#title")


def test_3d_canvas_is_not_blank(page, tmp_path):
    time.sleep(1.0)
    shot = tmp_path / "scene.png"
    page.locator("#scene3d").screenshot(path=str(shot))
    import cv2
    img = cv2.imread(str(shot))
    background = np.array([0x1a, 0x17, 0x15])  # BGR of the scene's background colour
    drawn = np.abs(img.astype(int) - background).sum(axis=2) > 30
    assert drawn.mean() > 0.01 and img.std() > 5, (drawn.mean(), img.std())  # a blank canvas gives 0


def test_the_mesh_is_shown_when_chosen(page, reconstructed, tmp_path):
    mesh = reconstructed[0].ws.load_dense_mesh()
    assert not page.is_disabled("#cloud option[value=mesh]")
    page.select_option("#cloud", "mesh")
    page.wait_for_function("() => window.fullview.shown && window.fullview.shown.kind === 'mesh'", timeout=15000)
    shown = page.evaluate("window.fullview.shown")
    assert shown["triangles"] == len(mesh["triangles"]) and shown["vertices"] == len(mesh["vertices"])
    assert f"{len(mesh['triangles']):,} triangles" in page.inner_text("#budget-label")
    time.sleep(1.0)
    shot = tmp_path / "mesh.png"
    page.locator("#scene3d").screenshot(path=str(shot))
    import cv2
    img = cv2.imread(str(shot))
    drawn = np.abs(img.astype(int) - np.array([0x1a, 0x17, 0x15])).sum(axis=2) > 30
    assert drawn.mean() > 0.01 and not page.problems, page.problems


# ------------------------------------------------------------------------------------------------ tour
def test_clicking_a_camera_opens_its_panorama(page, reconstructed):
    names, _ = _poses(reconstructed[0])
    x, y = page.evaluate(f"window.fullview.cameraScreenPosition({json.dumps(names[1])})")
    page.mouse.click(x, y)
    page.wait_for_function(f"() => window.fullview.tour && window.fullview.tour.ready && "
                           f"window.fullview.tour.name === {json.dumps(names[1])}", timeout=15000)
    assert page.is_visible("#tour")


def test_hotspot_moves_to_that_neighbour_keeping_the_world_direction(page, reconstructed):
    pipeline = reconstructed[0]
    names, sparse = _poses(pipeline)
    page.evaluate(f"window.fullview.tour = null")
    page.click("button[data-tab=scene]")
    x, y = page.evaluate(f"window.fullview.cameraScreenPosition({json.dumps(names[0])})")
    page.mouse.click(x, y)
    page.wait_for_function("() => window.fullview.tour && window.fullview.tour.ready", timeout=15000)
    target = names[2]
    spot = next(h for h in page.evaluate("window.fullview.tour.hotspots") if h["name"] == target)
    page.evaluate(f"window.fullview.tourLookAt({{yaw: {spot['yaw']}, pitch: {min(0.0, spot['pitch'] + 0.4)}}})")
    hotspot = page.locator(f".hotspot[data-target={json.dumps(target)}]")  # labels are room names or numbers
    before = page.evaluate("window.fullview.tourPosition()")
    hotspot.click()
    page.wait_for_function(f"() => window.fullview.tour.ready && window.fullview.tour.name === {json.dumps(target)}",
                           timeout=15000)
    after = page.evaluate("window.fullview.tourPosition()")
    R, i, j = sparse["R_cam_from_world"], 0, 2
    b = np.array([np.cos(before["pitch"]) * np.sin(before["yaw"]), -np.sin(before["pitch"]),
                  np.cos(before["pitch"]) * np.cos(before["yaw"])])
    lon, lat = bearings_to_lonlat(R[j] @ (R[i].T @ b))
    assert abs(np.angle(np.exp(1j * (after["yaw"] - lon)))) < 1e-3 and abs(after["pitch"] - lat) < 1e-3


def test_hotspots_point_at_the_neighbours(reconstructed, server):
    pipeline = reconstructed[0]
    names, sparse = _poses(pipeline)
    state = call(server, "api/state")
    cam = state["model"]["cameras"][0]
    R, c = sparse["R_cam_from_world"], sparse["centers"]
    for nb in cam["neighbours"]:
        j = names.index(nb["name"])
        lon, lat = bearings_to_lonlat(R[0] @ (c[j] - c[0]))
        assert np.isclose(nb["yaw"], lon, atol=1e-9) and np.isclose(nb["pitch"], lat, atol=1e-9)


# ------------------------------------------------------------------------------------------------ correlated views
def test_epipolar_circle_and_marker_where_python_puts_them(page, reconstructed):
    pipeline = reconstructed[0]
    names, sparse = _poses(pipeline)
    page.click("button[data-tab=corr]")
    page.wait_for_timeout(1500)
    R, c, points = sparse["R_cam_from_world"], sparse["centers"], sparse["points"]
    W, H = pipeline.dataset.image_sizes[names[0]]
    # a sparse point seen in front of camera 0 near the middle of the image (not at the poles)
    b = (points - c[0]) @ R[0].T
    px = bearings_to_pixels(b / np.linalg.norm(b, axis=1, keepdims=True), W, H)
    central = np.flatnonzero((px[:, 1] > 0.3 * H) & (px[:, 1] < 0.7 * H) & (px[:, 0] > 0.1 * W) & (px[:, 0] < 0.9 * W))
    k = central[0]
    x, y = page.evaluate(f"window.fullview.viewPagePosition({json.dumps(names[0])}, {px[k, 0]}, {px[k, 1]})")
    page.mouse.click(x, y)
    page.wait_for_function("() => window.fullview.lastClick !== null", timeout=10000)
    click = page.evaluate("window.fullview.lastClick")
    clicked = np.array(click["pixel"])
    ray = R[0].T @ pixels_to_bearings(clicked[None], W, H)[0]
    for j in (1, 2):
        other = names[j]
        circle = np.concatenate([np.array(seg) for seg in click["circles"][other]])
        # every pixel Python puts on the plane through c0, cj and the ray lies on the drawn circle
        normal = R[j] @ np.cross(ray, c[j] - c[0])
        on_plane = pixels_to_bearings(circle, W, H) @ (normal / np.linalg.norm(normal))
        assert np.abs(on_plane).max() < 1e-6
        # and the circle passes through the projection of the clicked scene point
        proj = bearings_to_pixels((R[j] @ (points[k] - c[j]))[None], W, H)[0]
        assert np.min(np.linalg.norm(circle - proj, axis=1)) < 3.0
        assert np.linalg.norm(np.array(click["markers"][other]) - proj) < 3.0
    assert np.allclose(click["point"], points[k], atol=1e-3 * np.ptp(points))


# ------------------------------------------------------------------------------------------------ picker
def test_picking_writes_hand_points_with_a_backup(page, reconstructed):
    pipeline = reconstructed[0]
    dataset = pipeline.dataset
    before = dataset.hand_points_path.read_text()
    names = dataset.image_names
    page.click("button[data-tab=corr]")
    page.wait_for_timeout(1000)
    page.check("#pick-mode")
    page.click("#new-track")
    clicks = {names[0]: (100.0, 120.0), names[1]: (300.0, 140.0)}
    for name, (x, y) in clicks.items():
        page.mouse.click(*page.evaluate(f"window.fullview.viewPagePosition({json.dumps(name)}, {x}, {y})"))
    page.click("#save-tracks")
    page.wait_for_function("() => window.fullview.saved === true", timeout=10000)
    data = yaml.safe_load(dataset.hand_points_path.read_text())
    new = data["points"][-1]
    assert set(new["observations"]) == set(clicks)
    for name, xy in clicks.items():
        assert np.allclose(new["observations"][name], xy, atol=1.0)
    backups = sorted(dataset.hand_points_path.parent.glob("hand_points.yaml.2*.bak"))  # timestamped, newest last
    assert backups and backups[-1].read_text() == before
    assert len(Dataset(dataset.root).hand_tracks()) == len(yaml.safe_load(before)["points"]) + 1


def test_a_server_killed_during_saves_leaves_a_valid_file(reconstructed, tmp_path, tiny_set_args):
    pipeline, _ = reconstructed
    data = tmp_path / "tiny"
    shutil.copytree(pipeline.dataset.root, data)
    ws = tmp_path / "ws"
    shutil.copytree(pipeline.ws.root, ws / "tiny")
    valid = {data.joinpath("hand_points.yaml").read_text()}
    points = yaml.safe_load(data.joinpath("hand_points.yaml").read_text())["points"]
    rng = np.random.default_rng(0)
    for trial in range(6):
        proc = subprocess.Popen([sys.executable, "-m", "fullview", "view", str(data), "-w", str(ws), "--no-browser",
                                 *tiny_set_args, *[a for s in SETTINGS for a in ("--set", s)]],
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        url = proc.stdout.readline().split()[-4]
        points[0]["name"] = f"renamed_{trial}"
        sender = threading.Thread(target=lambda: _ignore_errors(call, url, "api/hand_points", {"points": points}),
                                  daemon=True)
        sender.start()
        time.sleep(float(rng.uniform(0.0, 0.05)))
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        text = data.joinpath("hand_points.yaml").read_text()
        Dataset(data).hand_tracks()  # parses: never a half-written file
        valid.add(text)


def _ignore_errors(fn, *args):
    try:
        fn(*args)
    except OSError:
        pass


# ------------------------------------------------------------------------------------------------ report
def test_report_opens_from_disk_with_every_section(reconstructed, browser):
    from fullview.commands.report import report
    pipeline = reconstructed[0]
    path = Path(report(pipeline))
    assert path == pipeline.ws.path("report_page") and path.exists()
    page = browser.new_page(viewport=VIEWPORT)
    problems, requests = [], []
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.on("request", lambda r: requests.append(r.url))
    page.goto(path.as_uri())
    page.wait_for_load_state("load")
    text = page.inner_text("body")
    for heading in ("Stages", "Verified pairs", "Cameras", "Sparse model", "Depth maps", "Metrics", "Viewer"):
        assert heading in text
    assert page.evaluate("[...document.images].every(i => i.complete && i.naturalWidth > 0)")
    assert page.evaluate("document.images.length") >= 3 + len(pipeline.dataset.image_names)
    assert not problems and all(u.startswith("file://") for u in requests), (problems, requests)
    page.close()


def test_hand_check_flags_the_point_far_from_its_epipolar_circle(reconstructed, server):
    pipeline = reconstructed[0]
    names, sparse = _poses(pipeline)
    R, c, points = sparse["R_cam_from_world"], sparse["centers"], sparse["points"]
    W, H = pipeline.dataset.image_sizes[names[0]]
    tracks = []
    for k in np.random.default_rng(0).choice(len(points), 12, replace=False):
        obs = {}
        for j in (0, 1):
            b = R[j] @ (points[k] - c[j])
            obs[names[j]] = bearings_to_pixels((b / np.linalg.norm(b))[None], W, H)[0].tolist()
        tracks.append({"name": f"t{k}", "observations": obs})
    tracks[3]["observations"][names[1]][1] += 25.0  # a wrong click: 25 px off its true position
    result = call(server, "api/hand_check", {"points": tracks})
    (pair,) = result["pairs"]
    assert {pair["a"], pair["b"]} == {names[0], names[1]}
    assert pair["flagged"] == [tracks[3]["name"]]



# ------------------------------------------------------------------------------------------------ bad states
def test_a_dataset_never_run_gets_a_message_not_a_blank_page(reconstructed, browser, tmp_path):
    pipeline, config = reconstructed
    fresh = Pipeline(pipeline.dataset, Workspace(tmp_path / "empty", pipeline.dataset.name), config)
    httpd = make_server(ViewerApp(fresh, config))
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    page = browser.new_page(viewport=VIEWPORT)
    problems = []
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: problems.append(str(e)))
    try:
        page.goto(page_url(httpd))
        page.wait_for_function("() => window.fullview && window.fullview.ready", timeout=30000)
        assert "not been reconstructed yet" in page.inner_text("#message") and page.is_visible("#message")
        assert not problems, problems
    finally:
        page.close()
        httpd.shutdown()
        httpd.server_close()


def test_a_workspace_that_changes_is_announced(page, reconstructed):
    pipeline = reconstructed[0]
    assert not page.is_visible("#changed")
    pipeline.run_stage("registration")  # a run commits a new registration while the page is open
    page.wait_for_selector("#changed", state="visible", timeout=10000)
