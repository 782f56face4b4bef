"""The cached stage runner: fingerprints decide what reruns, like DVC.

A stage's fingerprint hashes its format version, its options, the fingerprints its upstream stages *should* have now,
the dataset inputs it reads (image contents, hand points), the source of the fullview modules its code reaches and
the versions of the numerical libraries. A stage is fresh when its manifest carries that fingerprint, the upstream
artifacts on disk are the ones it was built from, and every output it recorded is on disk unchanged (size on every
check; sha256 before a run consumes it). Anything else is stale, with the reason, or missing.

`run_cached` gives commands (the COLMAP reference run of `fullview compare`) the same cache and transactions.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import json
import logging
import resource
import sys
import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Callable

from threadpoolctl import ThreadpoolController

from fullview.io.config import Config, params_of
from fullview.io.dataset import Dataset
from fullview.io.errors import FullviewError
from fullview.io.workspace import StageWriter, Workspace
from fullview.stages import PIPELINE
from fullview.stages.protocol import Mapper, StageContext, cpu_seconds, thread_map

log = logging.getLogger(__name__)


class RunnerError(FullviewError, RuntimeError):
    """The requested run cannot proceed (unknown stage, stale upstream with --only, ...)."""


def stage_module(name: str):
    if name not in PIPELINE:
        raise RunnerError(f"unknown stage {name!r} (stages: {', '.join(PIPELINE)})")
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


def cached_state(ws: Workspace, folder: str, fingerprint: str, *, deep: bool) -> tuple[str, list[str], dict | None]:
    """(state, reasons, manifest) of a cached folder against the fingerprint it should have."""
    manifest, problem = ws.manifest(folder)
    if problem:
        return "stale", [problem], None
    if manifest is None:
        return "missing", ["never run"], None
    if manifest["fingerprint"] != fingerprint:
        return "stale", ["fingerprint differs"], manifest
    damaged = ws.verify(folder, manifest, deep=deep)
    if damaged:
        return "stale", [damaged], manifest
    return "fresh", [], manifest


def run_cached(ws: Workspace, folder: str, record: dict, produce: Callable[[StageWriter], dict], *,
               force: bool = False) -> dict:
    """The manifest of `folder`, produced by `produce(writer) -> summary` unless a verified run of the same record
    is on disk. Needs the run lock."""
    fingerprint = record_fingerprint(record)
    state, reasons, manifest = cached_state(ws, folder, fingerprint, deep=True)
    if state == "fresh" and not force:
        log.info("%s fresh, reusing %s", folder, ws.folder(folder))
        return manifest
    log.info("%s %s (%s): running", folder, state, "; ".join(reasons) or "forced")
    t0 = time.perf_counter()
    with ws.transaction(folder) as out:
        summary = produce(out)
        manifest = out.commit_manifest({**record, "fingerprint": fingerprint, "upstream": record.get("upstream", {}),
                                        "wall_time_s": round(time.perf_counter() - t0, 3), "summary": summary})
    return manifest


class Pipeline:
    """Fingerprints, status and execution of the stages for one dataset and config."""

    def __init__(self, dataset: Dataset, workspace: Workspace, config: Config, *, map: Mapper = thread_map):
        self.dataset, self.ws, self.config = dataset, workspace, config
        self.map = map  # how stages fan work out: local threads, or a Dask cluster under `fullview batch`
        self._fingerprints: dict[str, str] = {}

    # ---------------------------------------------------------------- fingerprints
    @cached_property
    def _input_hashes(self) -> dict[str, dict]:
        # Hashes of what the stages use: hand points parsed from the bytes hashed (one read), images and masks
        # pinned to the files validated and hashed (`Dataset._pinned`): a file replaced meanwhile stops the run
        # instead of filing a result under the other file's hash. Memoised for the run.
        return {
            "images": {name: self.dataset.image_hash(name) for name in self.dataset.image_names},
            "hand_points": {"hand_points.yaml": self.dataset.hand_points_hash()},
            "masks": self.dataset.mask_hashes(),
        }

    def fingerprint_record(self, stage: str) -> dict:
        module = stage_module(stage)
        return {
            "stage": stage,
            "version": module.VERSION,
            "params": params_of(self.config[stage]),
            "upstream": {u: self.fingerprint(u) for u in module.UPSTREAM},
            "inputs": {kind: self._input_hashes[kind] for kind in module.INPUTS},
            "code": code_hashes(module),
            "libraries": LIBRARY_VERSIONS,
        }

    def refresh(self) -> None:
        """Forget memoised fingerprints and input hashes (a long-lived reader such as the viewer calls this when
        the dataset may have changed)."""
        self._fingerprints.clear()
        self.__dict__.pop("_input_hashes", None)
        self.dataset.refresh_inputs()

    def fingerprint(self, stage: str) -> str:
        # Memoised: the chain asks for every upstream fingerprint again, and the inputs cannot change meanwhile.
        if stage not in self._fingerprints:
            self._fingerprints[stage] = record_fingerprint(self.fingerprint_record(stage))
        return self._fingerprints[stage]

    # ---------------------------------------------------------------- status
    def status(self, stage: str, *, deep: bool = False) -> StageStatus:
        """Fresh, stale or missing; `deep` checks output hashes, not only sizes."""
        state, reasons, manifest = cached_state(self.ws, stage, self.fingerprint(stage), deep=deep)
        if state == "stale" and manifest is not None and reasons == ["fingerprint differs"]:
            reasons = self._stale_reasons(stage, manifest)
        if state == "fresh":
            # The artifacts it was built from must still be the ones on disk (an upstream stage may have been
            # rerun alone with other settings since).
            rebuilt = [u for u in stage_module(stage).UPSTREAM
                       if (self.ws.read_manifest(u) or {}).get("fingerprint") != manifest["upstream"].get(u)]
            if rebuilt:
                return StageStatus(name=stage, state="stale",
                                   reasons=[f"upstream {u} on disk is not the one it was built from" for u in rebuilt])
        return StageStatus(name=stage, state=state, reasons=reasons)

    def chain_status(self, stage: str) -> StageStatus:
        """The status of `stage` and everything upstream of it, hashes checked: the first stage that is not fresh,
        else `stage`'s (fresh) status. What a command must see before it consumes a stage's artifacts."""
        for name in [*self._upstream_chain(stage), stage]:
            status = self.status(name, deep=True)
            if status.state != "fresh":
                return StageStatus(name=stage, state=status.state,
                                   reasons=[f"{name}: {r}" for r in status.reasons] if name != stage else status.reasons)
        return status

    def _stale_reasons(self, stage: str, manifest: dict) -> list[str]:
        now = self.fingerprint_record(stage)
        reasons = []
        if manifest.get("version") != now["version"]:
            reasons.append(f"format version {manifest.get('version')} -> {now['version']}")
        old_params = manifest.get("params") if isinstance(manifest.get("params"), dict) else {}
        for key in sorted(set(old_params) | set(now["params"])):
            if old_params.get(key) != now["params"].get(key):
                reasons.append(f"param {stage}.{key}: {old_params.get(key)!r} -> {now['params'].get(key)!r}")
        for up, fp in now["upstream"].items():
            if manifest["upstream"].get(up) != fp:
                reasons.append(f"upstream {up} changed")
        if manifest.get("libraries") != now["libraries"]:
            reasons.append(f"libraries changed: {manifest.get('libraries')} -> {now['libraries']}")
        old_code = manifest.get("code") if isinstance(manifest.get("code"), dict) else {}
        changed = sorted(k for k in set(old_code) | set(now["code"]) if old_code.get(k) != now["code"].get(k))
        if changed:
            reasons.append(f"code changed: {', '.join(changed)}")
        old_inputs = manifest.get("inputs") if isinstance(manifest.get("inputs"), dict) else {}
        for kind, hashes in now["inputs"].items():
            old = old_inputs.get(kind) if isinstance(old_inputs.get(kind), dict) else {}
            changed = sorted(k for k in set(old) | set(hashes) if old.get(k) != hashes.get(k))
            if changed:
                reasons.append(f"{kind} changed: {', '.join(changed[:5])}{' ...' if len(changed) > 5 else ''}")
        return reasons or ["fingerprint differs"]

    # ---------------------------------------------------------------- execution
    def run(self, *, start: str | None = None, until: str | None = None, only: str | None = None,
            force: bool = False, wait: bool = False) -> list[str]:
        """Run stale/missing stages in order under the workspace lock; returns the names of the stages that ran."""
        for name in (start, until, only):
            if name is not None:
                stage_module(name)
        if only is not None and (start is not None or until is not None):
            raise RunnerError("--only cannot be combined with --from or --until")
        if force and (start is not None or only is not None):
            raise RunnerError("--force reruns every stage; it cannot be combined with --from or --only")
        if start is not None and until is not None and PIPELINE.index(start) > PIPELINE.index(until):
            raise RunnerError(f"--from {start} comes after --until {until}")
        self.dataset.validate_inputs()  # bad images, hand points or masks fail now, not after hours of matching
        with self.ws.locked(wait=wait, command="fullview run"):
            return self._run_locked(start, until, only, force)

    def _run_locked(self, start, until, only, force) -> list[str]:
        if only is not None:
            for up in self._upstream_chain(only):
                st = self.status(up, deep=True)
                if st.state != "fresh":
                    raise RunnerError(f"--only {only}: upstream stage {up} is {st.state} "
                                      f"({'; '.join(st.reasons)}); run it first")
            self.run_stage(only)
            return [only]
        order = list(PIPELINE)
        last = order.index(until) + 1 if until else len(order)
        first_forced = order.index(start) if start else (0 if force else len(order))
        ran = []
        for k, stage in enumerate(order[:last]):
            st = None if k >= first_forced else self.status(stage, deep=True)
            if st is None or st.state != "fresh":
                if st is not None:
                    log.info("%-13s %s: %s", stage, st.state, "; ".join(st.reasons))
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
        return [s for s in PIPELINE if s in seen]

    def run_stage(self, stage: str) -> dict:
        module = stage_module(stage)
        log.info("%-13s running", stage)
        record = self.fingerprint_record(stage)  # what the run is built from, taken before it reads anything
        fingerprint = self.fingerprint(stage)
        t0, cpu0 = time.perf_counter(), cpu_seconds()
        # Single-threaded BLAS: our solvers make many small calls, which OpenBLAS threads only slow down (4-10x on
        # a loaded 2-core machine); stages parallelise over pairs or images themselves where it pays.
        with self.ws.locked(command=f"fullview run ({stage})"), self.ws.transaction(stage) as out, \
                _blas_controller().limit(limits=1, user_api="blas"):
            summary = module.run(StageContext(options=self.config[stage], dataset=self.dataset, ws=self.ws, out=out,
                                              map=self.map))
            manifest = out.commit_manifest({
                **record,
                "fingerprint": fingerprint,
                "wall_time_s": round(time.perf_counter() - t0, 3),
                # every thread of this process (a stage's own fan-out); on a shared machine it moves less than wall
                "cpu_time_s": round(cpu_seconds() - cpu0, 3),
                "peak_rss_mb": peak_rss_mb(),
                "summary": summary,
            })
        log.info("%-13s done in %.1f s %s", stage, manifest["wall_time_s"], _short(summary))
        return manifest


def peak_rss_mb() -> float:
    """The largest resident set of this process or of any reaped child process so far (MB). A forked worker's
    counts the parent's pages it shares and touches, so this is the peak of one process, not of their sum."""
    peaks = (resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return round(max(peaks) / 1024, 1)


_BLAS_CONTROLLER: tuple[int, ThreadpoolController] | None = None


def _blas_controller() -> ThreadpoolController:
    """threadpoolctl's view of the loaded BLAS libraries, found again only when modules were imported since (only
    an import loads a BLAS library): its scan resolves the path of every loaded shared library (~150 here, 2-15 ms),
    which `threadpool_limits` repeated for every stage."""
    global _BLAS_CONTROLLER
    if _BLAS_CONTROLLER is None or _BLAS_CONTROLLER[0] != len(sys.modules):
        _BLAS_CONTROLLER = (len(sys.modules), ThreadpoolController())
    return _BLAS_CONTROLLER[1]


def _short(summary: dict) -> str:
    items = [f"{k}={v}" for k, v in summary.items() if isinstance(v, (int, float, str))]
    return ", ".join(items[:6])
