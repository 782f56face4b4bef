"""Installed like a tool: `pip install .` builds a wheel that works outside the repo, the viewer's page and the
vendored libraries it loads included.

The wheel is built from a copy of the sources (setuptools writes build/ and *.egg-info beside them) without build
isolation, so no package index is needed (the test extras pin a setuptools that builds wheels by itself); it is then
unpacked and imported from a folder outside the repo with PYTHONPATH set to the unpacked tree, not installed."""

from __future__ import annotations

import glob
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
WEB = ROOT / "viewer" / "web"
TIMEOUT_S = 600
# what a copy of the sources leaves out: what no wheel holds (the vendored files are copied by pyproject's list)
_NOT_SOURCES = shutil.ignore_patterns(".git", ".venv", "workspace", "__pycache__", "build", "*.egg-info", "node_modules",
                                      ".pytest_cache", "results", "tests")


def _builds_wheels() -> bool:
    return (importlib.util.find_spec("setuptools.command.bdist_wheel") is not None
            or importlib.util.find_spec("wheel") is not None)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    if not (WEB / "node_modules" / "three").is_dir():
        pytest.skip("viewer/web/node_modules is absent: `make setup` vendors the viewer's libraries")
    if not _builds_wheels():
        pytest.skip("this setuptools cannot build a wheel (no bdist_wheel): `make setup` installs the pinned one")
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    shutil.copytree(ROOT, src, ignore=_NOT_SOURCES)
    for pattern in PYPROJECT["tool"]["setuptools"]["package-data"]["fullview.viewer"]:
        for path in glob.glob(str(ROOT / "viewer" / pattern)):
            target = src / Path(path).relative_to(ROOT)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, target)
    out = tmp / "dist"
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation",
                           "--no-index", "-w", str(out)], capture_output=True, text=True, timeout=TIMEOUT_S)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    wheels = list(out.glob("fullview-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def test_the_wheel_holds_every_module_and_the_command(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    packages = PYPROJECT["tool"]["setuptools"]["packages"]
    for package in packages:
        folder = ROOT.joinpath(*package.split(".")[1:])
        for module in folder.glob("*.py"):
            assert f"{package.replace('.', '/')}/{module.name}" in names, f"{module} is not in the wheel"
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "fullview = fullview.cli:main" in zipfile.ZipFile(wheel).read(entry_points).decode()
    assert "fullview/pipeline.yaml" in names and "fullview/benchmarks/baseline.json" in names
    assert not any(n.startswith(("fullview/tests/", "fullview/.venv/", "fullview/workspace/")) for n in names)


def _vendor_urls() -> set[str]:
    """Every vendored file the page loads: index.html's /vendor/ links and import map, app.js's imports through that
    map, and each vendored module's relative imports, as paths under viewer/web/node_modules."""
    html = (WEB / "index.html").read_text()
    imports = dict(re.findall(r'"([^"]+)":\s*"(/vendor/[^"]+)"', html))
    wanted = {u[len("/vendor/"):] for u in re.findall(r'href="(/vendor/[^"]+)"', html)}
    specifiers = set(re.findall(r"""from\s+['"]([^'"]+)['"]""", (WEB / "app.js").read_text()))
    todo = []
    for spec in specifiers:
        prefix = max((k for k in imports if spec == k or (k.endswith("/") and spec.startswith(k))), key=len)
        todo.append((imports[prefix] + spec[len(prefix):])[len("/vendor/"):])
    while todo:
        rel = todo.pop()
        if rel in wanted:
            continue
        wanted.add(rel)
        text = (WEB / "node_modules" / rel).read_text(encoding="utf-8")
        todo += [os.path.normpath(str(Path(rel).parent / r)) for r in
                 re.findall(r"""(?:from|import)\s*['"](\.{1,2}/[^'"]+)['"]""", text)]
    return wanted


def test_the_wheel_holds_the_viewer_page_and_every_vendored_file_it_loads(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for page in ("index.html", "app.js", "style.css"):
        assert f"fullview/viewer/web/{page}" in names
    wanted = _vendor_urls()
    assert {"three/build/three.module.js", "three/build/three.core.js"} <= wanted  # the parse found the chain
    missing = sorted(rel for rel in wanted if f"fullview/viewer/web/node_modules/{rel}" not in names)
    assert not missing, f"the page loads vendored files the wheel lacks: {missing}"


def test_the_unpacked_wheel_runs_outside_the_repo(wheel, tmp_path):
    unpacked, elsewhere = tmp_path / "site", tmp_path / "elsewhere"
    zipfile.ZipFile(wheel).extractall(unpacked)
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(unpacked)}
    probe = ("import fullview, fullview.cli; from fullview.viewer.server import VENDOR, VENDORED, WEB; "
             "print(fullview.__file__); print(all((VENDOR / p).is_dir() for p in VENDORED) and "
             "(WEB / 'index.html').is_file())")
    proc = subprocess.run([sys.executable, "-c", probe], cwd=elsewhere, env=env, capture_output=True, text=True,
                          timeout=TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr[-3000:]
    where, vendored = proc.stdout.split()
    assert Path(where).is_relative_to(unpacked), f"imported {where}, not the wheel's"
    assert vendored == "True"
    proc = subprocess.run([sys.executable, "-m", "fullview", "synth", elsewhere / "scene", "--views", "2",
                           "--width", "64"], cwd=elsewhere, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
    assert proc.returncode == 0 and (elsewhere / "scene" / "images").is_dir(), proc.stderr[-3000:]
