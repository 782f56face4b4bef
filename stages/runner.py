"""The cached stage runner: fingerprints decide what reruns, like DVC.

A stage's fingerprint hashes its format version, its config section, the fingerprints its upstream stages *should*
have now, the dataset inputs it reads (image contents, hand points) and the source of the fullview modules its code
reaches (so a fix in `sfm/` reruns the stages that use it, and only those). A stage is fresh when its manifest carries
that fingerprint; otherwise it is stale (with the reason) or missing. Running a stage makes everything downstream of
it stale through the chained fingerprints, while editing one stage's config never touches the stages before it.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import json
import logging
import resource
import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from threadpoolctl import threadpool_limits

from fullview.io.config import STAGE_ORDER
from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace

log = logging.getLogger(__name__)

PIPELINE_STAGES = STAGE_ORDER


class RunnerError(RuntimeError):
    """The requested run cannot proceed (unknown stage, stale upstream with --only, ...)."""


def stage_module(name: str):
    if name not in PIPELINE_STAGES:
        raise RunnerError(f"unknown stage {name!r} (stages: {', '.join(PIPELINE_STAGES)})")
    return importlib.import_module(f"fullview.stages.{name}")


def record_fingerprint(record: dict) -> str:
    """Short sha256 of a JSON-able record (key order does not matter)."""
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:16]


def _library_versions() -> dict[str, str]:
    import cv2
    import numpy
    import scipy

    return {"numpy": numpy.__version__, "scipy": scipy.__version__, "opencv": cv2.__version__}


LIBRARY_VERSIONS = _library_versions()  # an upgrade of these changes results, so it reruns the stages


def code_hashes(module) -> dict[str, str]:
    """sha256 (short) of the source of `module` and of every fullview module it reaches through its globals."""
    seen: dict[str, str] = {}
    todo = [module]
    while todo:
        mod = todo.pop()
        if mod.__name__ in seen or not mod.__name__.startswith("fullview.") or not getattr(mod, "__file__", None):
            continue
        seen[mod.__name__] = hashlib.sha256(Path(mod.__file__).read_bytes()).hexdigest()[:12]
        for value in vars(mod).values():
            dep = value if inspect.ismodule(value) else inspect.getmodule(value)
            if dep is not None and dep.__name__.startswith("fullview."):
                todo.append(dep)
    return dict(sorted(seen.items()))


@dataclass(kw_only=True)
class StageStatus:
    name: str  # stage name
    state: str  # fresh | stale | missing
    reasons: list[str]  # why it is stale or missing


class Pipeline:
    """Fingerprints, status and execution of the stages for one dataset and config."""

    def __init__(self, dataset: Dataset, workspace: Workspace, config: dict):
        self.dataset, self.ws, self.config = dataset, workspace, config
        self._fingerprints: dict[str, str] = {}

    # ---------------------------------------------------------------- fingerprints
    @cached_property
    def _input_hashes(self) -> dict[str, dict]:
        return {
            "images": {name: self.dataset.image_hash(name) for name in self.dataset.image_names},
            "hand_points": {"hand_points.yaml": self.dataset.hand_points_hash()},
        }

    def inputs_of(self, stage: str) -> dict:
        return {kind: self._input_hashes[kind] for kind in stage_module(stage).INPUTS}

    def fingerprint_record(self, stage: str) -> dict:
        module = stage_module(stage)
        return {
            "stage": stage,
            "version": module.VERSION,
            "params": self.config[stage],
            "upstream": {u: self.fingerprint(u) for u in module.UPSTREAM},
            "inputs": self.inputs_of(stage),
            "code": code_hashes(module),
            "libraries": LIBRARY_VERSIONS,
        }

    def fingerprint(self, stage: str) -> str:
        # Memoised: the chain asks for every upstream fingerprint again, and the inputs cannot change meanwhile.
        if stage not in self._fingerprints:
            self._fingerprints[stage] = record_fingerprint(self.fingerprint_record(stage))
        return self._fingerprints[stage]

    # ---------------------------------------------------------------- status
    def status(self, stage: str) -> StageStatus:
        manifest = self.ws.read_manifest(stage)
        if manifest is None:
            return StageStatus(name=stage, state="missing", reasons=["never run"])
        if manifest.get("fingerprint") == self.fingerprint(stage):
            # Also the artifacts it was built from must still be the ones on disk (an upstream stage may have been
            # rerun alone with other settings since).
            rebuilt = [u for u in stage_module(stage).UPSTREAM
                       if (self.ws.read_manifest(u) or {}).get("fingerprint") != manifest["upstream"].get(u)]
            if not rebuilt:
                return StageStatus(name=stage, state="fresh", reasons=[])
            return StageStatus(name=stage, state="stale",
                               reasons=[f"upstream {u} on disk is not the one it was built from" for u in rebuilt])
        return StageStatus(name=stage, state="stale", reasons=self._stale_reasons(stage, manifest))

    def _stale_reasons(self, stage: str, manifest: dict) -> list[str]:
        now = self.fingerprint_record(stage)
        reasons = []
        if manifest.get("version") != now["version"]:
            reasons.append(f"format version {manifest.get('version')} -> {now['version']}")
        old_params = manifest.get("params", {})
        for key in sorted(set(old_params) | set(now["params"])):
            if old_params.get(key) != now["params"].get(key):
                reasons.append(f"param {stage}.{key}: {old_params.get(key)!r} -> {now['params'].get(key)!r}")
        for up, fp in now["upstream"].items():
            if manifest.get("upstream", {}).get(up) != fp:
                reasons.append(f"upstream {up} changed")
        if manifest.get("libraries") != now["libraries"]:
            reasons.append(f"libraries changed: {manifest.get('libraries')} -> {now['libraries']}")
        old_code = manifest.get("code", {})
        changed = sorted(k for k in set(old_code) | set(now["code"]) if old_code.get(k) != now["code"].get(k))
        if changed:
            reasons.append(f"code changed: {', '.join(changed)}")
        for kind, hashes in now["inputs"].items():
            old = manifest.get("inputs", {}).get(kind, {})
            changed = sorted(k for k in set(old) | set(hashes) if old.get(k) != hashes.get(k))
            if changed:
                reasons.append(f"{kind} changed: {', '.join(changed[:5])}{' ...' if len(changed) > 5 else ''}")
        return reasons or ["fingerprint differs"]

    # ---------------------------------------------------------------- execution
    def run(self, *, start: str | None = None, until: str | None = None, only: str | None = None,
            force: bool = False) -> list[str]:
        """Run stale/missing stages in order; returns the names of the stages that ran."""
        self.ws.clean_leftovers()
        if only is not None:
            for up in self._upstream_chain(only):
                if self.status(up).state != "fresh":
                    raise RunnerError(f"--only {only}: upstream stage {up} is {self.status(up).state}; run it first")
            self.run_stage(only)
            return [only]
        order = list(PIPELINE_STAGES)
        last = order.index(until) + 1 if until else len(order)
        first_forced = order.index(start) if start else (0 if force else len(order))
        ran = []
        for k, stage in enumerate(order[:last]):
            if k >= first_forced or self.status(stage).state != "fresh":
                self.run_stage(stage)
                ran.append(stage)
            else:
                log.info("%-13s fresh, skipped", stage)
        return ran

    def _upstream_chain(self, stage: str) -> list[str]:
        """Every stage `stage` depends on, directly or not, in pipeline order."""
        todo, seen = list(stage_module(stage).UPSTREAM), set()
        while todo:
            up = todo.pop()
            if up not in seen:
                seen.add(up)
                todo.extend(stage_module(up).UPSTREAM)
        return [s for s in PIPELINE_STAGES if s in seen]

    def run_stage(self, stage: str) -> dict:
        module = stage_module(stage)
        log.info("%-13s running", stage)
        record = self.fingerprint_record(stage)  # what the run is built from, taken before it reads anything
        fingerprint = self.fingerprint(stage)
        t0 = time.perf_counter()
        # Single-threaded BLAS: our solvers make many small calls, which OpenBLAS threads only slow down (4-10x on
        # a loaded 2-core machine); stages parallelise over pairs or images themselves where it pays.
        with self.ws.stage_transaction(stage) as out_dir, threadpool_limits(limits=1, user_api="blas"):
            summary = module.run(config=self.config[stage], dataset=self.dataset, ws=self.ws, out_dir=out_dir)
            manifest = {
                **record,
                "fingerprint": fingerprint,
                "outputs": sorted(str(p.relative_to(out_dir)) for p in out_dir.rglob("*") if p.is_file()),
                "wall_time_s": round(time.perf_counter() - t0, 3),
                "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                "summary": summary,
            }
            self.ws.write_manifest(out_dir, manifest)
        log.info("%-13s done in %.1f s %s", stage, manifest["wall_time_s"], _short(summary))
        return manifest


def _short(summary: dict) -> str:
    items = [f"{k}={v}" for k, v in summary.items() if isinstance(v, (int, float, str))]
    return ", ".join(items[:6])
