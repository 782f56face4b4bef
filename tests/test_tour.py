"""The virtual tour in a real headless browser (Debian's chromium through Playwright), on a rendered three-room home
reconstructed with depth: hotspots never overlap at any heading, every neighbour in sight has one (or lies behind a
nearer one), none leads through a wall (checked against the scene's own geometry), hotspots lie on the floor below
their panorama, the tour tab opened directly shows a panorama, the 3-D view opens framed on the model's bounds with
its ceiling cut; on 360_Flat (../shared), walking by the nearest hotspot ahead visits the corridor's cameras in
order. Plus the layout and point-order rules on their own (viewer/tour.py)."""

from __future__ import annotations

import itertools
import json
import shutil
import threading
import urllib.error
from pathlib import Path

import numpy as np
import pytest
import yaml

from fullview import synth
from fullview.io.config import load_config
from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace
from fullview.sfm.camera import pixels_to_bearings
from fullview.stages.runner import Pipeline
from fullview.synth import write_synthetic_dataset
from fullview.viewer import tour
from fullview.viewer.server import VENDOR, ViewerApp, make_server, page_url

from tests.conftest import SHARED, TINY_OVERRIDES
from tests.test_viewer import call

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (make setup)")
DENSE = ["densify.working_width=512", "densify.rect_height=256", "densify.min_pair_inliers=30"]
VIEWPORT = {"width": 1400, "height": 900}
HEADINGS = 24
PITCHES_DEG = (0.0, -35.0, -70.0)  # level, towards the floor, down at the near hotspots
CLEARANCE = 0.15  # m: a ground-truth line of sight counts as free (blocked) when it stays so shifted this far
FLAT = SHARED / "openmvg-360" / "360_Flat"
FLAT_WORKSPACE = Path("/tmp/tour/flat")  # a run of 360_Flat reused when present (fullview run ... -w this)


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="session")
def home(tmp_path_factory):
    """The rendered three-room home (6 panoramas, 512 px), reconstructed through densify."""
    root = tmp_path_factory.mktemp("tour")
    data = write_synthetic_dataset(root / "home", views=6, width=512, seed=0, kind="home", rooms=3)
    config = load_config(None, TINY_OVERRIDES + DENSE)
    dataset = Dataset(data)
    pipeline = Pipeline(dataset, Workspace(root / "ws", dataset.name), config)
    pipeline.run()
    return pipeline, config


def _serve(pipeline, config):
    httpd = make_server(ViewerApp(pipeline, config))
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    return httpd


@pytest.fixture(scope="module")
def server(home):
    httpd = _serve(*home)
    yield page_url(httpd)
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture(scope="module")
def state(server):
    return call(server, "api/state", timeout=300)


@pytest.fixture(scope="module")
def browser():
    if CHROMIUM is None or not (VENDOR / "three").is_dir():
        pytest.skip("chromium or viewer/web/node_modules missing (make setup)")
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--use-gl=swiftshader", "--enable-unsafe-swiftshader"])
        yield b
        b.close()


def _open(browser, url, hash_="", wait="ready"):
    page = browser.new_page(viewport=VIEWPORT)
    page.problems = []
    page.on("console", lambda m: page.problems.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: page.problems.append(str(e)))
    page.goto(url + hash_)
    if wait:
        page.wait_for_function(f"() => window.fullview && window.fullview.{wait}", timeout=300000)
    return page


def _show(page, name):
    page.evaluate(f"window.fullview.openTour({json.dumps(name)})")
    page.wait_for_function(f"() => window.fullview.tour && window.fullview.tour.ready && "
                           f"window.fullview.tour.name === {json.dumps(name)}", timeout=60000)


def _look(page, yaw, pitch):
    page.evaluate(f"window.fullview.tourLookAt({{yaw: {yaw}, pitch: {pitch}}})")
    page.evaluate("() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")


def _overlap(a, b) -> bool:
    return a["left"] < b["right"] and b["left"] < a["right"] and a["top"] < b["bottom"] and b["top"] < a["bottom"]


def _gt(pipeline):
    """Ground truth: image -> centre, the scene's boxes and its floor height (world y, pointing down)."""
    root = pipeline.dataset.root
    cams = yaml.safe_load((root / "ground_truth" / "poses.yaml").read_text())["cameras"]
    scene = np.load(root / "ground_truth" / "scene.npz")
    centres = {c["image"]: np.array(c["center"]) for c in cams}
    R = {c["image"]: np.array(c["R_world_from_cam"]) for c in cams}
    return centres, R, scene["boxes"], float(scene["boxes"][0][1][1])


def _free(a, b, boxes) -> bool:
    rel = b - a
    dist = float(np.linalg.norm(rel))
    t, _ = synth.cast_rays(a, (rel / dist)[None], boxes)
    return bool(t[0] >= dist - 1e-6)


def _sight(a, b, boxes) -> str:
    """"free" when the segment a-b and its copies shifted CLEARANCE sideways and up/down all pass the scene's
    boxes, "blocked" when they all hit one, else "edge" (a line of sight grazing a door frame: not judged)."""
    side = np.cross(b - a, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    shifts = [np.zeros(3)] + [s * CLEARANCE * v for v in (side, np.array([0.0, 1.0, 0.0])) for s in (-1, 1)]
    free = [_free(a + d, b + d, boxes) for d in shifts]
    return "free" if all(free) else "blocked" if not any(free) else "edge"


# ------------------------------------------------------------------------------------------------ the layout on its own
def test_placed_hotspots_clear_each_other_and_the_nearer_one_stays():
    rng = np.random.default_rng(0)
    b = rng.normal(size=(60, 3))
    b[:, 1] = np.abs(b[:, 1]) + 0.3  # below the horizon, as floor points are
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    candidates = [{"name": str(k), "bearing": b[k], "distance": float(d)}
                  for k, d in enumerate(rng.uniform(0.5, 6, len(b)))]
    placed, left = tour.place_hotspots(candidates, 0.25)
    assert placed and left  # 60 discs do not fit: some are left out
    for p, q in itertools.combinations(placed, 2):
        sep = np.arccos(np.clip(np.dot(p["bearing"], q["bearing"]), -1, 1))
        assert sep >= p["radius"] + q["radius"]
    by_name = {p["name"]: p for p in placed}
    for lo in left:  # each left-out one lies behind a nearer hotspot that is kept
        assert by_name[lo["behind"]]["distance"] <= candidates[int(lo["name"])]["distance"]
    assert min(p["radius"] for p in placed) >= np.radians(tour.MIN_RADIUS_DEG) - 1e-12


def test_every_prefix_of_the_point_order_is_spread_over_the_model():
    rng = np.random.default_rng(1)
    dense = rng.normal(0, 0.05, size=(50000, 3))  # a dense blob ...
    sparse = rng.uniform(-1, 1, size=(2000, 3)) * [4, 1, 1]  # ... and a long, thin, sparse part
    points = np.vstack([dense, sparse])
    order, readable = tour.spatial_order(points, 0)
    assert sorted(order) == list(range(len(points)))
    extent = np.ptp(points, axis=0).max()

    def cells(p, n):
        return {tuple(c) for c in np.floor((p - points.min(0)) / (extent / n)).astype(int)}

    occupied = cells(points, tour.READABLE_CELLS)
    assert cells(points[order[:readable]], tour.READABLE_CELLS) == occupied  # the readable prefix covers every cell
    assert readable < len(points) / 2
    random_prefix = points[rng.permutation(len(points))[:readable]]
    assert len(cells(random_prefix, tour.READABLE_CELLS)) < 0.9 * len(occupied)  # first-N of a shuffle does not


# ------------------------------------------------------------------------------------------------ the data
def test_hotspots_link_every_neighbour_in_sight_and_none_behind_a_wall(home, state):
    pipeline = home[0]
    centres, _, boxes, _ = _gt(pipeline)
    cams = {c["name"]: c for c in state["model"]["cameras"]}
    judged = {"free": 0, "blocked": 0}
    for a, b in itertools.permutations(cams, 2):
        sight = _sight(centres[a], centres[b], boxes)
        spots = {h["name"] for h in cams[a]["hotspots"]}
        behind = {lo["name"]: lo["reason"] for lo in cams[a]["left_out"]}
        if sight == "blocked":
            judged["blocked"] += 1
            assert b not in spots, (a, b, "a hotspot through a wall")
        elif sight == "free":
            judged["free"] += 1
            assert b in spots or behind.get(b, "").startswith("behind the hotspot"), (a, b, behind.get(b))
    assert judged["free"] >= 6 and judged["blocked"] >= 6, judged  # the home has both kinds


def test_hotspots_lie_on_the_floor_below_their_panorama(home, state):
    pipeline = home[0]
    centres, R_world_from_cam, _, floor_y = _gt(pipeline)
    errors = []
    for cam in state["model"]["cameras"]:
        for h in cam["hotspots"]:
            spot = centres[h["name"]].copy()
            spot[1] = floor_y  # the floor below it (world y points down)
            b = R_world_from_cam[cam["name"]].T @ (spot - centres[cam["name"]])
            b /= np.linalg.norm(b)
            shown = np.array([np.cos(h["pitch"]) * np.sin(h["yaw"]), -np.sin(h["pitch"]),
                              np.cos(h["pitch"]) * np.cos(h["yaw"])])
            errors.append(np.degrees(np.arccos(np.clip(b @ shown, -1, 1))))
    assert errors and max(errors) < 0.5 * tour.MIN_RADIUS_DEG, errors  # inside the smallest disc drawn


def test_room_names_come_from_tour_yaml_as_text(home, tmp_path):
    pipeline, config = home
    data = tmp_path / "home"
    shutil.copytree(pipeline.dataset.root, data)
    names = pipeline.dataset.image_names
    (data / "tour.yaml").write_text(yaml.safe_dump({"names": {names[1]: "<b>Hall</b>"}}))
    moved = Pipeline(Dataset(data), pipeline.ws, config)
    from fullview.viewer.scene import SceneData
    cams = {c["name"]: c for c in SceneData(moved).state()["model"]["cameras"]}
    assert cams[names[1]]["label"] == "<b>Hall</b>" and cams[names[0]]["label"] == "1"
    assert all(h["label"] == "<b>Hall</b>" for c in cams.values() for h in c["hotspots"] if h["name"] == names[1])
    (data / "tour.yaml").write_text("names: {nope.png: Kitchen}\n")
    model = SceneData(moved).state()["model"]
    assert "unknown image 'nope.png'" in model["tour"]["names_problem"]
    assert model["cameras"][1]["label"] == "2"


def test_a_distance_measured_from_the_depth_agrees_with_the_truth_within_its_stated_error(home, server):
    pipeline = home[0]
    centres, R_world_from_cam, _, _ = _gt(pipeline)
    poses, _ = pipeline.ws.load_poses()
    names = [str(n) for n in poses["image_names"]]
    gt_c = np.array([centres[n] for n in names])
    i, j = np.triu_indices(len(names), 1)  # the model's scale, from the true camera centres (the viewer has none)
    model = poses["centers"]
    scale = np.median(np.linalg.norm(gt_c[i] - gt_c[j], axis=1) / np.linalg.norm(model[i] - model[j], axis=1))
    name = names[0]
    truth_range = np.load(pipeline.dataset.root / "ground_truth" / "depth" / f"{Path(name).stem}.npy")
    H, W = truth_range.shape
    valid = pipeline.ws.load_depth(name)["valid"]
    assert valid.shape == truth_range.shape  # densify at the panoramas' width: pixels are the same
    ys, xs = np.nonzero(valid[5:-5, 5:-5])
    ys, xs = ys + 5, xs + 5
    smooth = np.array([truth_range[y - 2:y + 3, x - 2:x + 3].std() < 0.02 * truth_range[y, x] for y, x in zip(ys, xs)])
    ys, xs = ys[smooth], xs[smooth]  # not across an edge of the true scene
    rng = np.random.default_rng(0)
    z = []
    for _ in range(15):
        a, b = rng.choice(len(ys), 2, replace=False)
        pa, pb = (xs[a] + 0.5, ys[a] + 0.5), (xs[b] + 0.5, ys[b] + 0.5)
        m = call(server, f"api/measure?image={name}&a={pa[0]},{pa[1]}&b={pb[0]},{pb[1]}")
        truth = [centres[name] + R_world_from_cam[name] @ (
            pixels_to_bearings(np.array([p], float), W, H)[0] * truth_range[int(p[1]), int(p[0])]) for p in (pa, pb)]
        true_d = np.linalg.norm(truth[0] - truth[1])
        z.append((m["distance"] * scale - true_d) / (m["sigma"] * scale))
        assert m["units"] == "model units" and m["sigma"] > 0
    assert np.all(np.abs(z) < 3), z  # the stated standard error covers the true error


def test_a_measurement_without_depth_is_refused_with_the_reason(home, server):
    pipeline = home[0]
    name = pipeline.dataset.image_names[0]
    valid = pipeline.ws.load_depth(name)["valid"]
    H, W = valid.shape
    free = np.ones_like(valid)
    for dy, dx in itertools.product(range(-2, 3), repeat=2):  # no valid depth within the 5x5 window
        free &= ~np.roll(np.roll(valid, dy, 0), dx, 1)
    y, x = np.argwhere(free[3:-3])[0] + [3, 0]
    with pytest.raises(urllib.error.HTTPError) as refused:
        call(server, f"api/measure?image={name}&a={x + 0.5},{y + 0.5}&b=10,100")
    assert refused.value.code == 409 and "no depth at point A" in json.loads(refused.value.read())["error"]


def test_cameras_placed_approximately_are_left_out_of_the_walk(home, tmp_path):
    pipeline, config = home
    ws_root = tmp_path / "ws"
    shutil.copytree(pipeline.ws.root, ws_root / pipeline.dataset.name)
    ws = Workspace(ws_root, pipeline.dataset.name)
    names = pipeline.dataset.image_names
    report_path = ws.path("registration_report")
    report = json.loads(report_path.read_text())
    report["placements"] = {n: {"verdict": "approximate" if n == names[1] else "verified"} for n in names}
    report_path.write_text(json.dumps(report))  # as registration writes it once verdicts exist
    from fullview.viewer.scene import SceneData
    model = SceneData(Pipeline(pipeline.dataset, ws, config)).state()["model"]
    cams = {c["name"]: c for c in model["cameras"]}
    assert not cams[names[1]]["walked"] and not cams[names[1]]["hotspots"]
    assert all(h["name"] != names[1] for c in cams.values() for h in c["hotspots"])
    assert model["tour"]["left_apart"] == [names[1]]
    assert all(cams[n]["walked"] for n in names if n != names[1])


# ------------------------------------------------------------------------------------------------ in the browser
def _no_overlap_anywhere(page, cameras):
    for cam in [c for c in cameras if c["walked"]]:
        _show(page, cam["name"])
        seen = set()
        for k, pitch in itertools.product(range(HEADINGS), PITCHES_DEG):
            _look(page, 2 * np.pi * k / HEADINGS, np.radians(pitch))
            boxes = page.evaluate("window.fullview.hotspotBoxes()")
            seen |= {b["target"] for b in boxes}
            for a, b in itertools.combinations(boxes, 2):
                assert not _overlap(a, b), (cam["name"], k, pitch, a, b)
        assert seen == {h["name"] for h in cam["hotspots"]}  # each one is drawn somewhere
    assert not page.problems, page.problems


def test_no_two_hotspots_overlap_at_any_heading(browser, server, state):
    page = _open(browser, server)
    try:
        _no_overlap_anywhere(page, state["model"]["cameras"])
    finally:
        page.close()


def test_the_tour_tab_opened_directly_shows_a_panorama(browser, server, state, tmp_path):
    page = _open(browser, server, "#tour", wait="tour && window.fullview.tour.ready")
    try:
        first = next(c["name"] for c in state["model"]["cameras"] if c["walked"])
        assert page.evaluate("window.fullview.tour.name") == first and page.is_visible("#tour")
        assert not page.is_visible("#tour-hint")
        page.wait_for_timeout(500)
        shot = tmp_path / "tour.png"
        page.locator("#tour").screenshot(path=str(shot))
        import cv2
        img = cv2.imread(str(shot))
        assert img.std() > 10, img.std()  # a panorama, not a blank page
        assert page.evaluate("window.fullview.hotspotBoxes().length") >= 1  # facing its nearest hotspot
    finally:
        page.close()


def test_the_tour_tab_clicked_before_anything_loaded_gives_a_hint_then_a_panorama(browser, server):
    page = browser.new_page(viewport=VIEWPORT)
    held = []
    page.route("**/api/state", lambda route: held.append(route))  # answered only when the test says so
    try:
        page.goto(server)
        page.wait_for_function("() => window.fullview !== undefined")
        page.click("button[data-tab=tour]")
        assert page.is_visible("#tour-hint") and "loading" in page.inner_text("#tour-hint")
        assert held and page.evaluate("window.fullview.tour") is None
        page.unroute("**/api/state")  # lets the held request through
        page.wait_for_function("() => window.fullview.tour && window.fullview.tour.ready", timeout=120000)
        assert not page.is_visible("#tour-hint") and page.is_visible("#tour")
        assert page.url.endswith("#tour")
    finally:
        page.close()


def test_the_3d_view_opens_framed_on_the_model_from_outside_with_its_ceiling_cut(browser, server, state):
    page = _open(browser, server)
    try:
        corners = np.array(page.evaluate("window.fullview.sceneFraming()"))
        assert len(corners) == 8 and np.all(np.abs(corners[:, :2]) <= 1) and np.all(corners[:, 2] < 1)
        t = state["model"]["tour"]
        lo, hi = np.array(t["bounds"])
        camera = np.array(page.evaluate("window.fullview.sceneCamera()"))
        assert np.any(camera < lo) or np.any(camera > hi)  # outside the model: a dollhouse, not inside the haze
        assert camera[1] > hi[1]  # and above it
        cut = page.evaluate("window.fullview.cut")
        assert t["floor"] < cut < t["ceiling"]  # the ceiling is cut away, the walls stay
        assert page.evaluate("window.fullview.shown.kind") == "mesh"
        assert not page.problems, page.problems
    finally:
        page.close()


def test_clicking_a_hotspot_walks_there_through_a_crossfade(browser, server, state):
    page = _open(browser, server)
    try:
        cam = next(c for c in state["model"]["cameras"] if c["walked"] and c["hotspots"])
        _show(page, cam["name"])
        target = cam["hotspots"][0]
        _look(page, target["yaw"], min(0.0, target["pitch"] + np.radians(25)))
        page.click(f".hotspot[data-target='{target['name']}']")
        page.wait_for_function(f"() => window.fullview.tour.ready && window.fullview.tour.name === "
                               f"{json.dumps(target['name'])}", timeout=60000)
        walk = page.evaluate("window.fullview.transitions")[-1]  # its duration is measured in the bench, not here
        assert walk["from"] == cam["name"] and walk["to"] == target["name"] and walk["fade_ms"] > 0
    finally:
        page.close()


# ------------------------------------------------------------------------------------------------ 360_Flat
@pytest.fixture(scope="module")
def flat_server(tmp_path_factory):
    if not FLAT.is_dir():
        pytest.skip(f"real data not found at {FLAT} (../shared)")
    dataset = Dataset(FLAT)
    config = load_config(None, [])
    cached = (FLAT_WORKSPACE / dataset.name / "densify").is_dir()
    ws_root = FLAT_WORKSPACE if cached else tmp_path_factory.mktemp("flat")
    pipeline = Pipeline(dataset, Workspace(ws_root, dataset.name), config)
    if ws_root != FLAT_WORKSPACE:
        pipeline.run()
    httpd = _serve(pipeline, config)
    yield page_url(httpd)
    httpd.shutdown()
    httpd.server_close()


def test_no_two_hotspots_overlap_at_any_heading_on_360_flat(browser, flat_server):
    page = _open(browser, flat_server)
    try:
        _no_overlap_anywhere(page, page.evaluate("window.fullview.state().model.cameras"))
    finally:
        page.close()


def test_walking_the_flat_corridor_by_the_nearest_hotspot_ahead_visits_every_camera_in_order(browser, flat_server):
    page = _open(browser, flat_server)
    try:
        cams = {c["name"]: c for c in page.evaluate("window.fullview.state().model.cameras")}
        corridor = sorted(n for n, c in cams.items() if c["walked"])
        _show(page, corridor[0])
        first = next(h for h in cams[corridor[0]]["hotspots"] if h["name"] == corridor[1])
        heading = first["yaw"]
        visited = [corridor[0]]
        while len(visited) < len(corridor):
            here = cams[visited[-1]]
            ahead = [h for h in here["hotspots"] if abs(np.angle(np.exp(1j * (h["yaw"] - heading)))) < np.pi / 3]
            if not ahead:
                break
            nxt = min(ahead, key=lambda h: h["distance"])
            _look(page, nxt["yaw"], min(0.0, nxt["pitch"] + np.radians(25)))
            box = next(b for b in page.evaluate("window.fullview.hotspotBoxes()") if b["target"] == nxt["name"])
            page.mouse.click((box["left"] + box["right"]) / 2, (box["top"] + box["bottom"]) / 2)  # a real click
            page.wait_for_function(f"() => window.fullview.tour.ready && window.fullview.tour.name === "
                                   f"{json.dumps(nxt['name'])}", timeout=60000)
            visited.append(nxt["name"])
            heading = page.evaluate("window.fullview.tourPosition()")["yaw"]  # the walk keeps the world direction
        assert visited == corridor
    finally:
        page.close()


def test_a_stated_scale_makes_the_measurement_metric_with_its_uncertainty(home, monkeypatch):
    """With a metric scale stated (export --camera-height), the same two clicks read in metres: the distance times
    the scale, its error widened by the scale's own."""
    from fullview.sfm.scale import Scale
    from fullview.viewer.scene import SceneData
    pipeline = home[0]
    scene = SceneData(pipeline)
    name = str(pipeline.ws.load_poses()[0]["image_names"][0])
    valid = pipeline.ws.load_depth(name)["valid"]
    ys, xs = np.nonzero(valid[5:-5, 5:-5])
    a, b = (xs[0] + 5.5, ys[0] + 5.5), (xs[-1] + 5.5, ys[-1] + 5.5)
    plain = scene.measure(name, a, b)
    scale = Scale(metres_per_unit=2.0, rel_std=0.05, method="camera height", stated="camera height 1.6 m",
                  measurements=6, spread=0.05)
    monkeypatch.setattr(SceneData, "metric_scale", lambda self, model: scale)
    metric = scene.measure(name, a, b)
    assert plain["units"] == "model units" and metric["units"] == "m"
    assert metric["distance"] == pytest.approx(2.0 * plain["distance"])
    assert metric["sigma"] == pytest.approx(np.hypot(2 * plain["sigma"], 0.05 * metric["distance"]))
