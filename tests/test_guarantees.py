"""Nothing a user does corrupts a workspace: each numbered reproduction of the hostile-tester report, then the
concurrency and kill -9 suites. docs/guarantees.md names these tests."""

from __future__ import annotations

import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from fullview.cli import main
from fullview.io.workspace import Workspace

pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
REPO = Path(__file__).resolve().parents[1]


def _cli(capsys, *args) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def _subprocess(*args, **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "fullview", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, **kw)


def _stderr_until(proc: subprocess.Popen, text: str, timeout: float) -> str:
    """The process's stderr lines up to the first containing `text` (all of it if the process ends first)."""
    lines: list[str] = []
    reader = threading.Thread(target=lambda: _read_until(proc.stderr, text, lines), daemon=True)
    reader.start()
    reader.join(timeout)
    return "".join(lines)


def _read_until(stream, text: str, lines: list[str]) -> None:
    for line in iter(stream.readline, ""):
        lines.append(line)
        if text in line:
            return


def _status(capsys, dataset, ws, settings) -> dict[str, str]:
    code, out, err = _cli(capsys, "status", dataset, "-w", ws, "--verify", *settings)
    assert code == 0, err
    return {line.split()[0]: line.split()[1] for line in out.splitlines()}


def _outputs(ws: Path, dataset_name: str, stages) -> dict:
    """Every output (size, sha256) the manifests record: equal dicts mean byte-identical artifacts."""
    return {s: json.loads((ws / dataset_name / s / "manifest.json").read_text())["outputs"] for s in stages}


SPARSE = ["features", "matches", "filter", "epipoles", "registration", "triangulation"]


# ------------------------------------------------------------------------------------------------ 1. two runs
def test_1_a_second_run_fails_fast_naming_the_holder(tiny_dataset, tmp_path, tiny_set_args):
    """This test process holds the lock as a live run would; the CLI run fails at once, naming it."""
    ws = Workspace(tmp_path / "ws", "tiny")
    with ws.locked(command="fullview run (test holder)"):
        second = _subprocess("run", tiny_dataset, "-w", tmp_path / "ws", "--only", "matches", *tiny_set_args)
        _, err = second.communicate(timeout=120)
    assert second.returncode == 2 and f"is in use by pid {os.getpid()} (fullview run (test holder)" in err, err
    assert "--wait" in err and "Traceback" not in err


def test_1_wait_takes_the_lock_when_the_holder_releases_it(tiny_dataset, tmp_path, tiny_set_args):
    ws = Workspace(tmp_path / "ws", "tiny")
    with ws.locked(command="holder"):
        waiting = _subprocess("run", tiny_dataset, "-w", tmp_path / "ws", "--until", "features", "--wait",
                              *tiny_set_args)
        # Release only once the run says it waits: on a loaded machine its start-up alone can take seconds.
        first_lines = _stderr_until(waiting, "waiting for pid", timeout=120)
        assert waiting.poll() is None  # still waiting
    _, err = waiting.communicate(timeout=120)
    assert waiting.returncode == 0, first_lines + err
    assert "waiting for pid" in first_lines


def test_1_concurrent_runs_leave_a_valid_fresh_workspace(tiny_dataset, tmp_path, tiny_set_args, capsys):
    """Staggered pairs of runs on one workspace, the second waiting or failing fast; then the workspace verifies."""
    ws = tmp_path / "ws"
    rng = np.random.default_rng(0)
    for trial in range(4):
        first = _subprocess("run", tiny_dataset, "-w", ws, "--until", "features" if trial % 2 else "matches",
                            "--force", *tiny_set_args)
        time.sleep(float(rng.uniform(0.5, 3.0)))
        extra = ["--wait"] if trial % 2 else []
        second = _subprocess("run", tiny_dataset, "-w", ws, "--until", "filter", *extra, *tiny_set_args)
        for proc in (first, second):
            proc.communicate(timeout=180)
        assert first.returncode == 0
        assert second.returncode in (0, 2) if not extra else second.returncode == 0
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "filter", *tiny_set_args]) == 0
    states = _status(capsys, tiny_dataset, ws, tiny_set_args)
    assert all(states[s] == "fresh" for s in ("features", "matches", "filter")), states
    assert not list((ws / "tiny").glob(".*.running.*"))


# ------------------------------------------------------------------------------------------------ 2. damage
@pytest.fixture
def filtered(tiny_dataset, tmp_path, tiny_set_args):
    ws = tmp_path / "ws"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "filter", *tiny_set_args]) == 0
    return tiny_dataset, ws


@pytest.mark.parametrize("damage", ["garbage", "deleted", "same_size"])
def test_2_corrupt_or_missing_artifacts_are_stale_and_rerun(filtered, tiny_set_args, capsys, damage):
    dataset, ws = filtered
    target = ws / "tiny" / "matches" / "matches.npz"
    if damage == "garbage":
        target.write_text("x\n")
    elif damage == "deleted":
        target = sorted((ws / "tiny" / "features").glob("*.npz"))[0]
        target.unlink()
    else:  # same size, other bytes: only the hash can tell
        data = bytearray(target.read_bytes())
        data[-10] ^= 0xFF
        target.write_bytes(bytes(data))
    code, out, _ = _cli(capsys, "status", dataset, "-w", ws, "--verify", *tiny_set_args)
    stage = target.parent.name
    line = next(l for l in out.splitlines() if l.startswith(stage))
    assert "stale" in line and target.name in line
    assert main(["run", str(dataset), "-w", str(ws), "--until", "filter", *tiny_set_args]) == 0
    assert all(v == "fresh" for k, v in _status(capsys, dataset, ws, tiny_set_args).items()
               if k in ("features", "matches", "filter"))


# ------------------------------------------------------------------------------------------------ 3. manifests
@pytest.mark.parametrize("text", ["[]", "{}", '{"fingerprint": "x"}', "not json", '{"fingerprint": "a", '
                                  '"upstream": {}, "outputs": {"x": 3}}'])
def test_3_malformed_manifests_are_stale_not_tracebacks(filtered, tiny_set_args, capsys, text):
    dataset, ws = filtered
    (ws / "tiny" / "matches" / "manifest.json").write_text(text)
    code, out, err = _cli(capsys, "status", dataset, "-w", ws, *tiny_set_args)
    assert code == 0 and "matches       stale" in out and "manifest" in out, out + err
    assert main(["run", str(dataset), "-w", str(ws), "--until", "filter", *tiny_set_args]) == 0
    assert _status(capsys, dataset, ws, tiny_set_args)["matches"] == "fresh"


# ------------------------------------------------------------------------------------------------ 4. no baseline
def test_4_identical_images_are_pairs_without_baseline(tiny_dataset, tmp_path, tiny_set_args, capsys):
    data = tmp_path / "same"
    (data / "images").mkdir(parents=True)
    first = sorted((tiny_dataset / "images").iterdir())[0]
    for k in range(3):
        shutil.copy(first, data / "images" / f"copy_{k}{first.suffix}")
    code, _, err = _cli(capsys, "run", data, "-w", tmp_path / "ws", *tiny_set_args)
    assert code == 2 and "nothing to register" in err, err
    summary = json.loads((tmp_path / "ws" / "same" / "filter" / "manifest.json").read_text())["summary"]
    assert len(summary["no_baseline_pairs"]) == 3


# ------------------------------------------------------------------------------------------------ 5. truncated
def test_5_a_truncated_jpeg_is_refused_before_any_stage(tiny_dataset, tmp_path, tiny_set_args, capsys):
    data = tmp_path / "cut"
    shutil.copytree(tiny_dataset, data)
    image = sorted((data / "images").iterdir())[0]
    ok, jpg = cv2.imencode(".jpg", cv2.imread(str(image)))
    image.unlink()
    cut = data / "images" / (image.stem + ".jpg")
    cut.write_bytes(jpg.tobytes()[: len(jpg) // 2])
    (data / "hand_points.yaml").unlink()
    code, _, err = _cli(capsys, "run", data, "-w", tmp_path / "ws", *tiny_set_args)
    _one_line_error(code, err, cut.name)
    assert not (tmp_path / "ws" / "cut" / "features").exists()


# ------------------------------------------------------------------------------------------------ 6. config
@pytest.mark.parametrize("override", ["densify.rect_height=0", "densify.block_size=4", "matches.ratio=.nan",
                                      "filter.threshold_deg=0", "features.working_width=7", "densify.neighbours=-1"])
def test_6_bad_config_values_stop_before_any_stage(tiny_dataset, tmp_path, capsys, override):
    code, _, err = _cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws", "--set", override)
    _one_line_error(code, err, override.split("=")[0])
    assert not (tmp_path / "ws" / "tiny" / "features").exists()


def test_6_min_latitude_above_max(tiny_dataset, tmp_path, capsys):
    code, _, err = _cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws", "--set", "features.min_latitude_deg=20",
                        "--set", "features.max_latitude_deg=10")
    assert code == 2 and "min_latitude_deg < max_latitude_deg" in err


# ------------------------------------------------------------------------------------------------ 7. environment
def _one_line_error(code, err, *needles):
    """Exit code 2 and exactly one error line (progress bars and warnings may precede it), no traceback."""
    assert code == 2, err
    errors = [line for line in err.splitlines() if line.startswith("fullview: error:")]
    assert len(errors) == 1 and "Traceback" not in err, err
    for n in needles:
        assert str(n) in errors[0], err


def test_7_workspace_path_is_a_file(tiny_dataset, tmp_path, capsys):
    (tmp_path / "ws").write_text("")
    _one_line_error(*_cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws")[::2], "ws")


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores file permissions")
def test_7_read_only_workspace(tiny_dataset, tmp_path, capsys):
    (tmp_path / "ws").mkdir()
    (tmp_path / "ws").chmod(0o500)
    try:
        _one_line_error(*_cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws")[::2], "Permission denied")
    finally:
        (tmp_path / "ws").chmod(0o700)


def test_7_permission_denied_is_one_line(tiny_dataset, tmp_path, capsys, monkeypatch):
    """As root the read-only test above cannot run: the same refusal, raised where the lock file is opened."""
    import errno

    import fullview.io.workspace as workspace
    real_open = os.open

    def denied(path, *args, **kwargs):
        if str(path).endswith(".lock"):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(workspace.os, "open", denied)
    _one_line_error(*_cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws")[::2], "Permission denied", ".lock")


def test_7_disk_full_is_one_line(tiny_dataset, tmp_path, capsys, monkeypatch):
    import errno

    import fullview.io.artifacts as artifacts

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "ws" / "x.npz"))

    monkeypatch.setattr(artifacts.np, "savez", full)
    _one_line_error(*_cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws", "--until", "features")[::2],
                    "No space left on device")
    assert not list((tmp_path / "ws" / "tiny").glob(".features.running.*"))


@pytest.mark.parametrize("args, needle", [
    (["-c", "{tmp}"], "not a file"), (["--set", "k=[1,"], "expected stage.key=value"),
    (["--set", "features.working_width=[1,"], "not valid YAML"), (["--only", "matches", "--from", "filter"], "--only"),
    (["--from", "registration", "--until", "matches"], "comes after"),
])
def test_7_bad_arguments(tiny_dataset, tmp_path, capsys, args, needle):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    _one_line_error(*_cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws", *args)[::2], needle)


@pytest.mark.parametrize("kind", ["folder", "broken_symlink"])
def test_7_odd_entries_in_images(dataset_copy, tmp_path, capsys, kind):
    entry = dataset_copy / "images" / "x.jpg"
    if kind == "folder":
        entry.mkdir()
    else:
        entry.symlink_to(tmp_path / "nowhere.jpg")
    _one_line_error(*_cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws")[::2], "x.jpg")


def test_7_status_into_a_closed_pipe(filtered, tiny_set_args):
    dataset, ws = filtered
    cmd = (f"{sys.executable} -m fullview status {dataset} -w {ws} {' '.join(tiny_set_args)} | head -1")
    proc = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], capture_output=True, text=True, timeout=120)
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr, proc.stderr
    assert proc.stdout.startswith("features")


# ------------------------------------------------------------------------------------------------ 8. eval
@pytest.fixture
def reconstructed_copy(dataset_copy, tmp_path, tiny_set_args):
    ws = tmp_path / "ws"
    assert main(["run", str(dataset_copy), "-w", str(ws), "--until", "triangulation", *tiny_set_args]) == 0
    return dataset_copy, ws


def _edit_ground_truth(dataset: Path, edit) -> None:
    import yaml
    path = dataset / "ground_truth" / "poses.yaml"
    data = yaml.safe_load(path.read_text())
    edit(data["cameras"])
    path.write_text(yaml.safe_dump(data))


@pytest.mark.parametrize("edit, needle", [
    (lambda cams: cams[0]["R_world_from_cam"][0].__setitem__(0, float("nan")), "R_world_from_cam"),
    (lambda cams: cams[1]["center"].__setitem__(2, float("nan")), "center"),
    (lambda cams: cams[1].__setitem__("center", list(cams[0]["center"])), "centre"),
])
def test_8_eval_refuses_bad_ground_truth(reconstructed_copy, tiny_set_args, capsys, edit, needle):
    dataset, ws = reconstructed_copy
    _edit_ground_truth(dataset, edit)
    code, out, err = _cli(capsys, "eval", dataset, "-w", ws, *tiny_set_args)
    _one_line_error(code, err, "poses.yaml")
    assert needle in err or needle.replace("re", "er") in err
    assert not (ws / "tiny" / "eval" / "metrics.json").exists()


def test_8_eval_refuses_a_stale_model(reconstructed_copy, tiny_set_args, capsys):
    dataset, ws = reconstructed_copy
    code, _, err = _cli(capsys, "eval", dataset, "-w", ws, *tiny_set_args, "--set", "filter.min_inliers=20")
    _one_line_error(code, err, "stale", "run the pipeline first")


# ------------------------------------------------------------------------------------------------ 9. smaller
def test_9_files_and_folders_honour_the_umask(tiny_dataset, tmp_path, tiny_set_args):
    old = os.umask(0o022)
    try:
        proc = subprocess.run([sys.executable, "-m", "fullview", "run", str(tiny_dataset), "-w", str(tmp_path / "ws"),
                               "--until", "features", *tiny_set_args], capture_output=True, text=True, timeout=120)
    finally:
        os.umask(old)
    assert proc.returncode == 0, proc.stderr
    folder = tmp_path / "ws" / "tiny" / "features"
    assert stat.S_IMODE(folder.stat().st_mode) == 0o755
    assert {stat.S_IMODE(p.stat().st_mode) for p in folder.iterdir()} == {0o644}


def test_9_a_mistyped_baseline_is_an_error(tiny_dataset, tmp_path, capsys):
    _one_line_error(*_cli(capsys, "compare", tiny_dataset, "-w", tmp_path / "ws", "--baseline",
                          tmp_path / "baselin.json")[::2], "baselin.json")


def test_9_negative_colmap_max_features(tiny_dataset, tmp_path, capsys):
    _one_line_error(*_cli(capsys, "colmap-check", tiny_dataset, "-w", tmp_path / "ws", "--colmap-max-features",
                          "-5")[::2], "--colmap-max-features")


def test_9_hand_points_are_checked_before_any_stage(dataset_copy, tmp_path, capsys):
    (dataset_copy / "hand_points.yaml").write_text("points:\n  - observations: {ghost.jpg: [1, 2]}\n")
    _one_line_error(*_cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws")[::2], "ghost.jpg")
    assert not (tmp_path / "ws" / "tiny" / "features").exists()


def test_9_internal_errors_exit_1_with_a_hint(tiny_dataset, tmp_path, capsys, monkeypatch):
    import fullview.stages.features as features

    monkeypatch.setattr(features, "detect_features", lambda *a: 1 / 0)
    code, _, err = _cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws", "--until", "features")
    assert code == 1 and "internal error: ZeroDivisionError" in err and "--debug" in err


# ------------------------------------------------------------------------------------------------ kill -9
def test_kill_9_at_random_moments_then_rerun_is_byte_identical(tiny_dataset, tmp_path, tiny_set_args):
    reference = tmp_path / "reference"
    assert main(["run", str(tiny_dataset), "-w", str(reference), "--until", "triangulation", *tiny_set_args]) == 0
    expected = _outputs(reference, "tiny", SPARSE)
    ws = tmp_path / "ws"
    rng = np.random.default_rng(1)
    for delay in rng.uniform(1.5, 6.0, size=3):
        proc = _subprocess("run", tiny_dataset, "-w", ws, "--until", "triangulation", *tiny_set_args)
        time.sleep(float(delay))
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "triangulation", *tiny_set_args]) == 0
    assert _outputs(ws, "tiny", SPARSE) == expected
    assert not list((ws / "tiny").glob(".*.running.*")) and not list((ws / "tiny").glob(".*.old.*"))


def test_reads_never_see_a_half_committed_stage(filtered):
    """The commit lock: a reader holding it delays the swap, so the manifest and files it reads belong together."""
    dataset, ws_root = filtered
    ws = Workspace(ws_root, "tiny")
    with ws.reading():
        manifest = ws.read_manifest("matches")
        assert ws.verify("matches", manifest, deep=True) is None


# ------------------------------------------------------------------------------------------------ review findings
def test_synth_never_replaces_a_folder_of_other_files(tmp_path, capsys):
    folder = tmp_path / "thesis"
    folder.mkdir()
    (folder / "chapter1.txt").write_text("precious")
    _one_line_error(*_cli(capsys, "synth", folder, "--views", "2", "--width", "64")[::2], "not empty")
    assert (folder / "chapter1.txt").read_text() == "precious"
    assert _cli(capsys, "synth", tmp_path / "new", "--views", "2", "--width", "64")[0] == 0
    assert _cli(capsys, "synth", tmp_path / "new", "--views", "2", "--width", "64")[0] == 0  # its own output: ok


def test_export_out_never_replaces_a_workspace_or_foreign_folder(reconstructed_copy, tiny_set_args, tmp_path, capsys):
    dataset, ws = reconstructed_copy
    args = ["export", dataset, "-w", ws, "--format", "ply", *tiny_set_args, "--out"]
    _one_line_error(*_cli(capsys, *args, ws / "tiny" / "triangulation")[::2], "inside the workspace")
    assert (ws / "tiny" / "triangulation" / "sparse.npz").exists()
    app = tmp_path / "webapp"
    app.mkdir()
    (app / "manifest.json").write_text("{}")
    (app / "index.html").write_text("<html>")
    _one_line_error(*_cli(capsys, *args, app)[::2], "not empty")
    assert (app / "index.html").exists()


def test_a_malformed_baseline_is_refused_before_colmap_runs(tiny_dataset, tmp_path, capsys):
    bad = tmp_path / "b.json"
    bad.write_text("[1]")
    _one_line_error(*_cli(capsys, "compare", tiny_dataset, "-w", tmp_path / "ws", "--baseline", bad)[::2], "b.json")
    assert not (tmp_path / "ws" / "tiny" / "colmap_spherical").exists()


def test_force_with_from_is_refused(tiny_dataset, tmp_path, capsys):
    _one_line_error(*_cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws", "--force", "--from", "matches")[::2],
                    "--force")


def test_manifest_outputs_must_stay_in_their_folder(filtered, tiny_set_args, capsys):
    dataset, ws = filtered
    path = ws / "tiny" / "matches" / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["outputs"]["/dev/zero"] = {"size": 0, "sha256": "0"}
    path.write_text(json.dumps(manifest))
    code, out, _ = _cli(capsys, "status", dataset, "-w", ws, "--verify", *tiny_set_args)
    assert code == 0 and "matches       stale" in out and "outside its folder" in out


@pytest.mark.parametrize("override", ["features.face_size=1000000", "features.max_features_per_face=99999999999"])
def test_huge_values_are_refused_not_internal_errors(tiny_dataset, tmp_path, capsys, override):
    _one_line_error(*_cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws", "--set", override)[::2],
                    override.split("=")[0])


def test_status_of_a_workspace_that_is_a_file(tiny_dataset, tmp_path, capsys):
    (tmp_path / "ws").write_text("")
    _one_line_error(*_cli(capsys, "status", tiny_dataset, "-w", tmp_path / "ws")[::2], "not a folder")
