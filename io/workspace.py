"""The workspace of one dataset: every output path, stage manifests and atomic stage commits.

Layout::

    <workspace>/<dataset name>/
        <stage>/manifest.json      fingerprint, params, inputs, outputs, summary (written last)
        features/<image stem>.npz  per-image features
        matches/matches.npz        raw matches of every pair
        filter/inliers.npz         F and epipolar inliers of every pair
        epipoles/epipoles.npz      relative poses of every pair
        registration/registration.npz, registration.json
        triangulation/sparse.npz, sparse.ply, colmap/{cameras,images,points3D}.txt
        densify/dense.ply, dense_preview.png, summary.json, depth/<stem>.npz, depth/<stem>.png
        colmap_check/check.json, check.md, faces/   (fullview colmap-check)
        colmap_spherical/model/                       (fullview compare: cached COLMAP reference)
        compare/colmap.json, colmap.md, top_view.png  (fullview compare)
        eval/metrics.json

A stage runs inside a temporary folder beside its final one; only a finished run replaces the previous folder, so an
interrupted run leaves the last good artifacts (and their manifest) in place.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from fullview.io.artifacts import save_json


class Workspace:
    """All paths of one dataset's outputs."""

    def __init__(self, root: Path, dataset_name: str):
        self.root = Path(root) / dataset_name

    def stage_dir(self, stage: str) -> Path:
        return self.root / stage

    def manifest_path(self, stage: str) -> Path:
        return self.stage_dir(stage) / "manifest.json"

    def read_manifest(self, stage: str) -> dict | None:
        path = self.manifest_path(stage)
        if not path.exists():
            return None
        try:
            return json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            return None  # unreadable manifest: the stage counts as missing

    # ---- artifact paths (the stage folder is passed explicitly while a stage runs in its temp folder)
    def features_path(self, image_name: str, stage_dir: Path | None = None) -> Path:
        return (stage_dir or self.stage_dir("features")) / f"{Path(image_name).stem}.npz"

    def matches_path(self, stage_dir: Path | None = None) -> Path:
        return (stage_dir or self.stage_dir("matches")) / "matches.npz"

    def inliers_path(self, stage_dir: Path | None = None) -> Path:
        return (stage_dir or self.stage_dir("filter")) / "inliers.npz"

    def epipoles_path(self, stage_dir: Path | None = None) -> Path:
        return (stage_dir or self.stage_dir("epipoles")) / "epipoles.npz"

    def registration_path(self, stage_dir: Path | None = None) -> Path:
        return (stage_dir or self.stage_dir("registration")) / "registration.npz"

    def sparse_path(self, stage_dir: Path | None = None) -> Path:
        return (stage_dir or self.stage_dir("triangulation")) / "sparse.npz"

    def colmap_dir(self, stage_dir: Path | None = None) -> Path:
        return (stage_dir or self.stage_dir("triangulation")) / "colmap"

    def dense_ply_path(self, stage_dir: Path | None = None) -> Path:
        return (stage_dir or self.stage_dir("densify")) / "dense.ply"

    def depth_dir(self, stage_dir: Path | None = None) -> Path:
        return (stage_dir or self.stage_dir("densify")) / "depth"

    def eval_path(self) -> Path:
        return self.root / "eval" / "metrics.json"

    @contextmanager
    def stage_transaction(self, stage: str) -> Iterator[Path]:
        """A fresh temporary folder for a stage run; swapped in for the old folder only on success."""
        self.root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{stage}.running.", dir=self.root))
        try:
            yield tmp
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        final = self.stage_dir(stage)
        old = None
        try:
            if final.exists():
                old = Path(tempfile.mkdtemp(prefix=f".{stage}.old.", dir=self.root))
                final.rename(old / stage)
            tmp.rename(final)
        except BaseException:
            if old is not None and not final.exists():
                (old / stage).rename(final)  # put the previous good folder back
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def write_manifest(self, stage_dir: Path, manifest: dict) -> None:
        save_json(stage_dir / "manifest.json", manifest)

    def clean_leftovers(self) -> None:
        """Remove temp folders of runs killed before they could clean up; restore a previous folder whose swap
        was cut short (its final folder is missing)."""
        if not self.root.exists():
            return
        for p in self.root.glob(".*.old.*"):
            for saved in p.iterdir():
                if not self.stage_dir(saved.name).exists():
                    saved.rename(self.stage_dir(saved.name))
            shutil.rmtree(p, ignore_errors=True)
        for p in self.root.glob(".*.running.*"):
            shutil.rmtree(p, ignore_errors=True)
