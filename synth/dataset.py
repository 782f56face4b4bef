"""Write a rendered synthetic scene as a dataset folder (see fullview.io.dataset for the layout)."""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
import yaml

from fullview.io.artifacts import save_npz
from fullview.synth.scene import SynthScene, render_scene

log = logging.getLogger(__name__)

SCENE_VERSION = 1


def write_synthetic_dataset(out: Path, *, views: int, width: int, seed: int) -> Path:
    """Render and write a scene; the folder appears complete or not at all."""
    out = Path(out)
    scene = render_scene(views=views, width=width, seed=seed)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        _write(tmp, scene, dict(views=views, width=width, seed=seed))
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info("synthetic dataset written to %s", out)
    return out


def _write(root: Path, scene: SynthScene, params: dict) -> None:
    (root / "images").mkdir()
    (root / "ground_truth" / "depth").mkdir(parents=True)
    for view in scene.views:
        if not cv2.imwrite(str(root / "images" / view.name), view.image):
            raise OSError(f"could not write {root / 'images' / view.name}")
        np.save(root / "ground_truth" / "depth" / f"{Path(view.name).stem}.npy", view.depth.astype(np.float32))
    cameras = [{"image": v.name, "R_world_from_cam": np.round(v.R_world_from_cam, 12).tolist(),
                "center": np.round(v.center, 12).tolist()} for v in scene.views]
    (root / "ground_truth" / "poses.yaml").write_text(yaml.safe_dump({"cameras": cameras}, sort_keys=False))
    (root / "hand_points.yaml").write_text(yaml.safe_dump({"points": _plain(scene.hand_points)}, sort_keys=False, default_flow_style=None))
    save_npz(root / "ground_truth" / "scene.npz", SCENE_VERSION, boxes=scene.boxes,
             scene_size=np.float64(scene.scene_size), **{k: np.int64(v) for k, v in params.items()})


def _plain(points: list[dict]) -> list[dict]:
    """Hand tracks with plain floats, so the YAML stays readable."""
    return [{"name": p["name"], "observations": {img: [round(float(x), 2), round(float(y), 2)]
                                                 for img, (x, y) in p["observations"].items()}} for p in points]
