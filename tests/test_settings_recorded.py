"""Settings live with the workspace: `run` records them (value and source per key) in <workspace>/settings.yaml,
every later command reads them, and a plain command finds the workspace from any folder (DATASET/.fullview/).
The repo's pipeline.yaml is a template equal to the code's defaults."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
import urllib.request
from pathlib import Path

import yaml

from fullview.cli import main
from fullview.io.dataset import Dataset
from fullview.io.config import default_config, load_config, params_of
from fullview.io.workspace import DATASET_WORKSPACE
from fullview.stages import PIPELINE

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 600  # a wedged subprocess fails the test instead of hanging it


def _cli(capsys, *args) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def _status(out: str) -> dict[str, str]:
    return {line.split()[0]: line.split()[1] for line in out.splitlines() if line.split()[0] in PIPELINE}


def _recorded(ws: Path) -> dict:
    return yaml.safe_load((ws / "settings.yaml").read_text())


def test_pipeline_yaml_is_the_code_defaults():
    """One source: the shipped template holds exactly the code's defaults, so `-c pipeline.yaml` and no file agree."""
    template, defaults = load_config(ROOT / "pipeline.yaml"), default_config()
    assert {s: params_of(o) for s, o in template.items()} == {s: params_of(o) for s, o in defaults.items()}


def test_run_records_every_key_with_its_source_and_plain_commands_use_them(tiny_dataset, tmp_path, capsys,
                                                                           tiny_set_args):
    ws = tmp_path / "ws"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "features", *tiny_set_args]) == 0
    recorded = _recorded(ws / "tiny")
    assert recorded["features"]["working_width"] == {"value": 512, "from": "--set"}
    assert recorded["features"]["max_features_per_face"] == {"value": 1500, "from": "default"}
    assert sum(len(v) for k, v in recorded.items() if k != "fullview_settings") == \
        sum(len(params_of(o)) for o in default_config().values())
    capsys.readouterr()
    code, out, _ = _cli(capsys, "status", tiny_dataset, "-w", ws)  # no --set: the recorded settings
    assert code == 0 and _status(out)["features"] == "fresh"
    assert "features.working_width = 512  (--set)" in out
    # a plain run changes nothing and reruns nothing
    code, out, err = _cli(capsys, "run", tiny_dataset, "-w", ws, "--until", "features")
    assert code == 0 and "nothing to run (all fresh)" in out
    assert _recorded(ws / "tiny") == recorded


def test_a_change_is_recorded_with_the_stages_it_makes_stale(tiny_dataset, tmp_path, capsys, tiny_set_args, caplog):
    ws = tmp_path / "ws"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "features", *tiny_set_args]) == 0
    caplog.clear()
    with caplog.at_level("INFO", logger="fullview"):
        assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "features", "--set", "filter.seed=3"]) == 0
    text = caplog.text
    assert "setting filter.seed: 0 -> 3 (--set)" in text
    assert "makes stale: filter, epipoles, registration, triangulation, densify" in text
    recorded = _recorded(ws / "tiny")
    assert recorded["filter"]["seed"] == {"value": 3, "from": "--set"}
    assert recorded["features"]["working_width"] == {"value": 512, "from": "--set"}  # earlier --set kept
    capsys.readouterr()
    code, out, _ = _cli(capsys, "status", tiny_dataset, "-w", ws)
    assert code == 0 and "filter.seed = 3  (--set)" in out and _status(out)["features"] == "fresh"


def test_c_replaces_the_recorded_settings_and_names_the_file(tiny_dataset, tmp_path, capsys, tiny_set_args):
    ws, config = tmp_path / "ws", tmp_path / "mine.yaml"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "features", *tiny_set_args,
                 "--set", "filter.seed=3"]) == 0
    config.write_text("features:\n  working_width: 512\n")
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "features", "-c", str(config)]) == 0
    recorded = _recorded(ws / "tiny")
    assert recorded["features"]["working_width"] == {"value": 512, "from": str(config.resolve())}
    assert recorded["filter"]["seed"] == {"value": 0, "from": "default"}  # not merged with the earlier record
    assert recorded["filter"]["threshold_deg"]["from"] == "default"


def test_a_recorded_key_that_no_longer_exists_is_one_line_naming_it(tiny_dataset, tmp_path, capsys, tiny_set_args):
    ws = tmp_path / "ws"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "features", *tiny_set_args]) == 0
    path = ws / "tiny" / "settings.yaml"
    recorded = _recorded(ws / "tiny")
    recorded["densify"]["mesh_smoothing"] = {"value": 3, "from": "--set"}
    path.write_text(yaml.safe_dump(recorded))
    capsys.readouterr()
    for command in ("status", "run", "export"):
        code, out, err = _cli(capsys, command, tiny_dataset, "-w", ws, *(("--format", "ply") if command == "export"
                                                                           else ()))
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and lines[0].startswith("fullview: error:"), err
        assert "densify.mesh_smoothing" in err and str(path) in err and "--reset-settings" in err
    assert "mesh_smoothing" in path.read_text()  # never a silent reset
    code, _, err = _cli(capsys, "run", tiny_dataset, "-w", ws, "--until", "features", "--reset-settings",
                        *tiny_set_args)
    assert code == 0, err
    assert "mesh_smoothing" not in path.read_text()


def test_a_recorded_default_that_changed_since_is_kept_and_shown(tiny_dataset, tmp_path, capsys, tiny_set_args):
    """The results on disk were made with the recorded value: it stays (they stay fresh), and status says that the
    default moved."""
    ws = tmp_path / "ws"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "features", *tiny_set_args]) == 0
    path = ws / "tiny" / "settings.yaml"
    recorded = _recorded(ws / "tiny")
    recorded["densify"]["min_texture_std"] = {"value": 1.5, "from": "default"}  # as an older default would be
    path.write_text(yaml.safe_dump(recorded))
    capsys.readouterr()
    code, out, _ = _cli(capsys, "status", tiny_dataset, "-w", ws)
    assert code == 0 and _status(out)["features"] == "fresh"
    default = default_config()["densify"].min_texture_std
    assert f"densify.min_texture_std = 1.5  (default when recorded; the default is now {default!r})" in out


def test_without_w_the_workspace_is_inside_the_dataset_whatever_the_folder(tiny_dataset, dataset_copy, tmp_path,
                                                                           capsys, monkeypatch, tiny_set_args):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    monkeypatch.chdir(tmp_path / "a")
    assert main(["run", str(dataset_copy), "--until", "features", *tiny_set_args]) == 0
    assert (dataset_copy / DATASET_WORKSPACE / "features" / "manifest.json").is_file()
    assert not (tmp_path / "a" / "workspace").exists()
    monkeypatch.chdir(tmp_path / "b")
    capsys.readouterr()
    code, out, _ = _cli(capsys, "status", os.path.relpath(dataset_copy))
    assert code == 0 and _status(out)["features"] == "fresh"
    assert f"workspace: {dataset_copy.resolve() / DATASET_WORKSPACE}" in out
    assert Dataset(dataset_copy).image_names == Dataset(tiny_dataset).image_names  # the workspace is no input


# ------------------------------------------------------------------------------------------------ done when
def _fullview(cwd: Path, *args) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.run([sys.executable, "-m", "fullview", *map(str, args)], cwd=cwd, env=env, text=True,
                          capture_output=True, timeout=TIMEOUT_S)
    assert proc.returncode == 0, f"fullview {' '.join(map(str, args))}: {proc.stderr[-2000:]}"
    return proc


def _view_briefly(cwd: Path, dataset: Path) -> tuple[str, str, bytes, dict | None]:
    """Start `fullview view --no-browser`, GET the URL it prints (and the scene state), stop it: (its log, the URL,
    the page, the state or None when the page's token rules keep the API from a plain GET)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "fullview", "view", str(dataset), "--no-browser"], cwd=cwd,
                            env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        found: list[str] = []
        reader = threading.Thread(target=lambda: found.extend(
            m.group(0) for line in iter(proc.stdout.readline, "") for m in [re.search(r"http://127\.0\.0\.1:\d+/\S*",
                                                                                       line)] if m), daemon=True)
        reader.start()
        for _ in range(TIMEOUT_S * 10):
            if found or proc.poll() is not None:
                break
            reader.join(0.1)
        assert found, f"view printed no URL: {proc.stderr.read() if proc.poll() is not None else ''}"
        url = found[0]
        with urllib.request.urlopen(url, timeout=60) as response:
            assert response.status == 200
            page = response.read()
        state_url = re.sub(r"^(http://[^/]+)/[^?]*", r"\1/api/state", url)
        try:
            with urllib.request.urlopen(state_url, timeout=60) as response:
                state = json.loads(response.read())
        except urllib.error.HTTPError as e:
            assert e.code in (401, 403), e  # a token the page sends by other means; the page itself was served
            state = None
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    return proc.stderr.read(), url, page, state


def _ply_elements(path: Path) -> dict[str, int]:
    """The element counts of a PLY file's header ({"vertex": N, "face": M})."""
    counts = {}
    with open(path, "rb") as f:
        for line in iter(f.readline, b""):
            words = line.decode("ascii").split()
            if words[:1] == ["element"]:
                counts[words[1]] = int(words[2])
            if words[:1] == ["end_header"]:
                return counts
    raise AssertionError(f"{path}: no PLY header end")


def test_done_when_plain_commands_from_another_folder_see_the_fresh_run(dataset_copy, tmp_path, tiny_set_args):
    """Issue 31's test: the pipeline run from a folder outside the repo with one --set (a densify mesh key, with the
    tiny settings as --set), then plain status, export --format ply, eval and view from another folder: all see
    the same fresh results, and the PLY export holds the dense cloud and the mesh."""
    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir()
    second.mkdir()
    assert ROOT not in first.parents and ROOT not in dataset_copy.parents
    run = _fullview(first, "run", dataset_copy, "--set", "densify.mesh_cell_voxels=3", *tiny_set_args)
    ws = dataset_copy.resolve() / DATASET_WORKSPACE
    assert f"workspace: {ws}" in run.stdout and "view: fullview view" in run.stdout
    assert re.search(r"mesh: \d+ vertices, \d+ triangles", run.stdout), run.stdout
    assert (ws / "report" / "index.html").is_file() and f"report: {ws / 'report' / 'index.html'}" in run.stdout
    assert f"<code>fullview view {dataset_copy}</code>" in (ws / "report" / "index.html").read_text()  # no -w needed
    dense_manifest = json.loads((ws / "densify" / "manifest.json").read_text())
    assert dense_manifest["params"]["mesh_cell_voxels"] == 3.0

    status = _fullview(second, "status", dataset_copy)
    assert _status(status.stdout) == {s: "fresh" for s in PIPELINE}, status.stdout
    assert "densify.mesh_cell_voxels = 3.0  (--set)" in status.stdout

    export = _fullview(second, "export", dataset_copy, "--format", "ply")
    out = Path(export.stdout.strip().splitlines()[-1])
    assert out == ws / "export_ply"
    assert {p.name for p in (out / "0").iterdir()} >= {"sparse.ply", "dense.ply", "dense_mesh.ply"}
    summary = dense_manifest["summary"]  # the export holds this run's cloud and mesh
    assert _ply_elements(out / "0" / "dense.ply")["vertex"] == summary["points"] > 0
    assert _ply_elements(out / "0" / "dense_mesh.ply")["face"] == summary["mesh"]["triangles"] > 0

    evaluated = json.loads(_fullview(second, "eval", dataset_copy).stdout)
    assert "dense_agreement" in evaluated, sorted(evaluated)  # densify is current for the recorded settings

    log, url, page, state = _view_briefly(second, dataset_copy)
    assert f"results of {ws}: every stage fresh" in log, log
    assert b"<html" in page.lower()
    if state is not None:
        assert {s: v["state"] for s, v in state["stages"].items()} == {s: "fresh" for s in PIPELINE}

    again = _fullview(second, "run", dataset_copy)  # a plain run keeps the --set: nothing to redo
    assert "nothing to run (all fresh)" in again.stdout
    assert json.loads((ws / "densify" / "manifest.json").read_text())["fingerprint"] == dense_manifest["fingerprint"]
