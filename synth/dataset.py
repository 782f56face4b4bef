"""Write a rendered synthetic scene as a dataset folder (see fullview.io.dataset for the layout)."""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
import yaml

from fullview.io.artifacts import apply_umask, save_npz
from fullview.io.errors import FullviewError
from fullview.io.workspace import make_dirs
from fullview.synth.capture import CaptureTraits
from fullview.synth.scene import SynthScene, crossing_hand_points, render_scene

log = logging.getLogger(__name__)

SCENE_VERSION = 1
SCENE_FILE = Path("ground_truth") / "scene.npz"  # what marks a folder as a synthetic dataset
HAND_POINT_MODES = ("all", "crossing", "none")
CROSSING_HAND_POINTS = 8  # tracks written with hand_points="crossing" (the fewest that seed a pair: 8-point F)


class SynthError(FullviewError):
    """The output folder of `fullview synth` cannot be used."""


def write_synthetic_dataset(out: Path, *, views: int, width: int, seed: int, kind: str = "room", rooms: int = 4,
                            closed_door: int | None = None, hand_points: str = "all",
                            capture: CaptureTraits | None = None) -> Path:
    """Render and write a scene (``kind``, ``rooms``, ``closed_door``: see ``render_scene``); the folder appears
    complete or not at all. An existing folder is replaced only when it is empty or a synthetic dataset written
    before (never a folder of other files).

    ``hand_points``: which tracks go to hand_points.yaml: ``"all"`` (every marker and corner seen by >= 2 views),
    ``"crossing"`` (home with a closed door only: the ``CROSSING_HAND_POINTS`` tracks seen by >= 2 views on each
    side of it, see ``crossing_hand_points``) or ``"none"`` (no hand_points.yaml). ``capture``: traits of a real
    capture (``fullview.synth.capture``), recorded in scene.npz when any is on."""
    out = Path(out).resolve()
    if hand_points not in HAND_POINT_MODES:
        raise SynthError(f"hand_points must be one of {', '.join(HAND_POINT_MODES)}, got {hand_points!r}")
    if hand_points == "crossing" and (kind != "home" or closed_door is None):
        raise SynthError("hand points 'crossing' need a home with a closed door (--scene home --closed-door K)")
    _check_replaceable(out)
    params = dict(views=views, width=width, seed=seed)
    if kind == "home":  # the room scene's scene.npz keeps its original keys
        params.update(rooms=rooms, closed_door=-1 if closed_door is None else closed_door)
    traits = {}
    if capture is not None and capture.any:  # the scene.npz of a clean render keeps its original keys
        traits = dict(tilt_deg=np.float64(capture.tilt_deg), exposure_stops=np.float64(capture.exposure_stops),
                      noise=np.float64(capture.noise), shuffle=np.bool_(capture.shuffle))
    scene = render_scene(views=views, width=width, seed=seed, kind=kind, rooms=rooms, closed_door=closed_door,
                         capture=capture)
    if hand_points == "crossing":
        try:
            tracks = crossing_hand_points(scene, closed_door, CROSSING_HAND_POINTS)
        except ValueError as e:
            raise SynthError(f"{out}: {e}") from None
    else:
        tracks = scene.hand_points if hand_points == "all" else None
    make_dirs(out.parent)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    apply_umask(tmp, directory=True)
    try:
        _write(tmp, scene, params, kind, tracks, traits)
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info("synthetic dataset written to %s", out)
    return out


def _check_replaceable(out: Path) -> None:
    if out == Path.cwd() or out in Path.cwd().parents:
        raise SynthError(f"{out}: is the current folder or contains it; choose a new folder")
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / SCENE_FILE).is_file())):
        raise SynthError(f"{out}: exists and is not empty nor a synthetic dataset; choose a new folder")


def _write(root: Path, scene: SynthScene, params: dict, kind: str, hand_points: list[dict] | None,
           traits: dict) -> None:
    (root / "images").mkdir()
    (root / "ground_truth" / "depth").mkdir(parents=True)
    for view in scene.views:
        if not cv2.imwrite(str(root / "images" / view.name), view.image):
            raise OSError(f"could not write {root / 'images' / view.name}")
        np.save(root / "ground_truth" / "depth" / f"{Path(view.name).stem}.npy", view.depth.astype(np.float32))
    cameras = [{"image": v.name, "R_world_from_cam": np.round(v.R_world_from_cam, 12).tolist(),
                "center": np.round(v.center, 12).tolist()} for v in scene.views]
    (root / "ground_truth" / "poses.yaml").write_text(yaml.safe_dump({"cameras": cameras}, sort_keys=False))
    if hand_points is not None:
        (root / "hand_points.yaml").write_text(yaml.safe_dump({"points": _plain(hand_points)}, sort_keys=False,
                                                              default_flow_style=None))
    save_npz(root / SCENE_FILE, SCENE_VERSION, boxes=scene.boxes,
             scene_size=np.float64(scene.scene_size), **{k: np.int64(v) for k, v in params.items()},
             **({"kind": np.str_(kind)} if kind != "room" else {}), **traits)


def _plain(points: list[dict]) -> list[dict]:
    """Hand tracks with plain floats, so the YAML stays readable."""
    return [{"name": p["name"], "observations": {img: [round(float(x), 2), round(float(y), 2)]
                                                 for img, (x, y) in p["observations"].items()}} for p in points]
