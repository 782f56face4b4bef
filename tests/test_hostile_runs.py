"""The hostile tester's runs, exports and processes (issue 30, items 5, 6, 7, 10 and parts of 11 and 13): a result is
never marked fresh for inputs it was not computed from, an export removes only what an earlier export of its own
wrote, COLMAP's text format never garbles a name, a killed run's children leave with it, a manifest that is no
regular file is stale, the PLY export says when the dense cloud is not current, and the hashed artifacts hold no
timings."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from fullview.cli import main
from fullview.io.dataset import Dataset
from fullview.io.workspace import RUN_LOCK, Workspace
from fullview.stages import protocol

pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
REPO = Path(__file__).resolve().parents[1]


def _cli(capsys, *args) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def _status(capsys, dataset, ws, settings) -> dict[str, list[str]]:
    code, out, err = _cli(capsys, "status", dataset, "-w", ws, "--verify", *settings)
    assert code == 0, err
    return {line.split()[0]: line.split()[1:] for line in out.splitlines() if line.strip()}


def _wait_for(condition, what: str, limit_s: float = 60.0) -> None:
    """Poll `condition` until it holds; fail naming `what` after `limit_s` (a bound on a hang, not a timing claim)."""
    end = time.monotonic() + limit_s
    while not condition():
        if time.monotonic() > end:
            pytest.fail(f"gave up waiting for {what}")
        time.sleep(0.05)


# ------------------------------------------------------------------------------------- 10. children die with the run
def _child_report(_: object) -> dict:
    """What a forked worker holds: its open descriptors' targets and its parent-death signal."""
    import ctypes

    libc = ctypes.CDLL(None)
    sig = ctypes.c_int(0)
    libc.prctl(2, ctypes.byref(sig), 0, 0, 0)  # PR_GET_PDEATHSIG
    fds = {}
    for fd in os.listdir("/proc/self/fd"):
        try:
            fds[fd] = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            pass
    return {"pdeathsig": sig.value, "fds": fds}


@pytest.mark.parametrize("how", ["forked", "process_map"])
def test_10_a_forked_child_holds_no_workspace_lock_and_dies_with_its_parent(tmp_path, how):
    if not sys.platform.startswith("linux"):
        pytest.skip("forked children are Linux only (other systems run the work on threads)")
    ws = Workspace(tmp_path / "ws", "ds")
    with ws.locked(command="test"), ws.reading():
        if how == "forked":
            with protocol.forked(_child_report, None) as job:
                report = job.result()
        else:
            report = list(protocol.process_map(_child_report, [1, 2], processes=2))[0]
    assert report["pdeathsig"] == signal.SIGKILL
    held = [t for t in report["fds"].values() if t.endswith((RUN_LOCK, ".fullview.commit.lock"))]
    assert held == [], f"the child holds the workspace's locks open: {held}"


DENSE = ["--set", "densify.working_width=512", "--set", "densify.rect_height=256", "--set",
         "densify.min_pair_inliers=30"]

# `fullview run` with the world planes' child (forked by densify) replaced by one that reports its pid and sleeps:
# a deterministic moment at which the run has a forked child, instead of a timed guess.
_SLOW_CHILD_RUN = textwrap.dedent("""
    import os, sys, time
    from fullview.stages import densify
    def asleep(*args):
        with open(os.environ["FULLVIEW_TEST_CHILD_PID"] + ".tmp", "w") as f:
            f.write(str(os.getpid()))
        os.replace(os.environ["FULLVIEW_TEST_CHILD_PID"] + ".tmp", os.environ["FULLVIEW_TEST_CHILD_PID"])
        time.sleep(600)
    densify._world_planes = asleep
    from fullview.cli import main
    sys.exit(main(sys.argv[1:]))
""")


@pytest.fixture(scope="module")
def sparse_ws(tiny_dataset, tmp_path_factory, tiny_set_args):
    """The tiny dataset reconstructed up to triangulation (read-only: copy the workspace before changing it)."""
    ws = tmp_path_factory.mktemp("sparse") / "ws"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "triangulation", *tiny_set_args]) == 0
    return ws


def _gone(pid: int) -> bool:
    """The process has ended (a zombie nobody reaped yet has closed its descriptors too)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def _lock_is_free(path: Path) -> bool:
    fd = os.open(path, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False
    finally:
        os.close(fd)


def test_10_kill_9_during_densify_leaves_no_child_holding_the_lock(tiny_dataset, sparse_ws, tmp_path, tiny_set_args,
                                                                   capsys):
    if not sys.platform.startswith("linux"):
        pytest.skip("forked children are Linux only")
    ws = tmp_path / "ws"
    shutil.copytree(sparse_ws, ws)
    marker = tmp_path / "child.pid"
    env = {**os.environ, "FULLVIEW_TEST_CHILD_PID": str(marker), "PYTHONPATH": os.pathsep.join(sys.path)}
    log = tmp_path / "run.log"
    with open(log, "w") as stderr:  # a file, not a pipe: the orphan would keep a pipe open after its parent died
        parent = subprocess.Popen([sys.executable, "-c", _SLOW_CHILD_RUN, "run", str(tiny_dataset), "-w", str(ws),
                                   "--until", "densify", *tiny_set_args, *DENSE], env=env,
                                  stdout=subprocess.DEVNULL, stderr=stderr)
    child = None
    try:
        _wait_for(lambda: marker.exists() or parent.poll() is not None, "densify to fork its child", 300)
        assert marker.exists(), f"the run ended before densify forked: {log.read_text()[-2000:]}"
        child = int(marker.read_text())
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=30)
        _wait_for(lambda: _gone(child), f"the orphaned child {child} to end with its parent", 20)
        _wait_for(lambda: _lock_is_free(ws / "tiny" / RUN_LOCK), "the run lock to be free", 20)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if child is not None and not _gone(child):
            os.kill(child, signal.SIGKILL)
    code, _, err = _cli(capsys, "run", tiny_dataset, "-w", ws, "--until", "triangulation", *tiny_set_args)
    assert code == 0 and "in use by" not in err, err


# ------------------------------------------------------------------------------- 11. manifests that are no files
@pytest.fixture
def filtered(tiny_dataset, tmp_path, tiny_set_args):
    ws = tmp_path / "ws"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "filter", *tiny_set_args]) == 0
    return tiny_dataset, ws


def _status_subprocess(dataset, ws, settings) -> subprocess.CompletedProcess:
    """`fullview status --verify` in a child process with a time bound (a hang fails the test, never the suite) and a
    memory bound (reading /dev/zero to the end would fail it instead of filling the machine)."""
    import resource

    def bounded():
        resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    return subprocess.run([sys.executable, "-m", "fullview", "status", str(dataset), "-w", str(ws), "--verify",
                           *settings], capture_output=True, text=True, timeout=120, env=env, preexec_fn=bounded)


@pytest.mark.parametrize("kind", ["dev_zero", "fifo", "output_fifo"])
def test_11_a_manifest_that_is_a_device_or_fifo_is_stale_not_a_hang(filtered, tiny_set_args, kind):
    dataset, ws = filtered
    target = ws / "tiny" / "matches" / ("matches.npz" if kind == "output_fifo" else "manifest.json")
    target.unlink()
    if kind == "dev_zero":
        target.symlink_to("/dev/zero")
    else:
        os.mkfifo(target)
    done = _status_subprocess(dataset, ws, tiny_set_args)
    assert done.returncode == 0, done.stderr
    line = next(l for l in done.stdout.splitlines() if l.startswith("matches"))
    assert "stale" in line and ("not a regular file" in line), line
    assert main(["run", str(dataset), "-w", str(ws), "--until", "filter", *tiny_set_args]) == 0
    assert "fresh" in next(l for l in _status_subprocess(dataset, ws, tiny_set_args).stdout.splitlines()
                           if l.startswith("matches"))


# --------------------------------------------------------------------------- 13. hashed outputs hold no timings
@pytest.fixture(scope="module")
def dense_ws(tiny_dataset, sparse_ws, tmp_path_factory, tiny_set_args):
    """The tiny dataset reconstructed through densify (read-only)."""
    ws = tmp_path_factory.mktemp("dense") / "ws"
    shutil.copytree(sparse_ws, ws)
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "densify", *tiny_set_args, *DENSE]) == 0
    return ws


def test_13_densify_rerun_writes_the_same_bytes_its_summary_without_timings(tiny_dataset, dense_ws, tmp_path,
                                                                            tiny_set_args):
    ws = tmp_path / "ws"
    shutil.copytree(dense_ws, ws)
    before = json.loads((ws / "tiny" / "densify" / "manifest.json").read_text())
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--from", "densify", "--until", "densify", *tiny_set_args,
                 *DENSE]) == 0
    after = json.loads((ws / "tiny" / "densify" / "manifest.json").read_text())
    assert after["outputs"] == before["outputs"]  # every hashed file, summary.json and the pictures included
    written = json.loads((ws / "tiny" / "densify" / "summary.json").read_text())
    keys = set()

    def walk(obj):
        if isinstance(obj, dict):
            keys.update(obj)
            [walk(v) for v in obj.values()]
        elif isinstance(obj, list):
            [walk(v) for v in obj]
    walk(written)
    assert not keys & {"time_s", "timings_s", "cpu_time_s", "wall_time_s", "phases_s", "median_pair_time_s"}
    assert written["points"] == after["summary"]["points"] and "phases_s" in after["summary"]  # the manifest has them


# ----------------------------------------------------------------- 5. fingerprints of the very inputs that were used
def _replace_right_after_the_read(monkeypatch, path: Path, data: bytes, cls, method: str) -> list[Path]:
    """Replace `path` by `data` (atomically, as the picker saves) once, right after the run's first `cls.method` call
    (the read that validates and hashes it) returns: the window in which the tester's save made a result fresh for
    the file it was not computed from."""
    done: list[Path] = []
    original = getattr(cls, method)

    def then_replace(self, *args, **kwargs):
        out = original(self, *args, **kwargs)
        if not done:
            tmp = path.with_name(path.name + ".new")
            tmp.write_bytes(data)
            os.replace(tmp, path)
            done.append(path)
        return out
    monkeypatch.setattr(cls, method, then_replace)
    return done


def test_5_hand_points_replaced_after_they_were_read_never_leave_a_fresh_result_of_the_old_file(
        dataset_copy, tmp_path, tiny_set_args, capsys, monkeypatch):
    import hashlib

    import yaml

    hand = dataset_copy / "hand_points.yaml"
    old = hand.read_bytes()
    points = yaml.safe_load(old)["points"]
    new = yaml.safe_dump({"points": points[: len(points) // 2]}, sort_keys=False).encode()
    ws = tmp_path / "ws"
    replaced = _replace_right_after_the_read(monkeypatch, hand, new, Dataset, "_read_hand_points")
    assert _cli(capsys, "run", dataset_copy, "-w", ws, "--until", "filter", *tiny_set_args)[0] == 0
    assert replaced and hand.read_bytes() == new
    manifest = json.loads((ws / "tiny" / "filter" / "manifest.json").read_text())
    # the result is filed under the bytes it was computed from: the file as it was when the run read it
    assert manifest["inputs"]["hand_points"]["hand_points.yaml"] == hashlib.sha256(old).hexdigest()
    status = _status(capsys, dataset_copy, ws, tiny_set_args)
    assert status["filter"][0] == "stale" and "hand_points changed" in " ".join(status["filter"]), status
    # and a rerun computes it for the new file
    monkeypatch.undo()
    assert _cli(capsys, "run", dataset_copy, "-w", ws, "--until", "filter", *tiny_set_args)[0] == 0
    assert _status(capsys, dataset_copy, ws, tiny_set_args)["filter"][0] == "fresh"
    manifest = json.loads((ws / "tiny" / "filter" / "manifest.json").read_text())
    assert manifest["inputs"]["hand_points"]["hand_points.yaml"] == hashlib.sha256(new).hexdigest()


def test_5_an_image_replaced_after_it_was_hashed_stops_the_run_naming_it(dataset_copy, tmp_path, tiny_set_args, capsys,
                                                                   monkeypatch):
    import cv2

    images = sorted((dataset_copy / "images").iterdir())
    flipped = cv2.imencode(images[0].suffix, cv2.imread(str(images[0]))[:, ::-1])[1].tobytes()  # valid, other pixels
    ws = tmp_path / "ws"
    replaced = _replace_right_after_the_read(monkeypatch, images[0], flipped, Dataset, "image_hash")
    code, _, err = _cli(capsys, "run", dataset_copy, "-w", ws, "--until", "features", *tiny_set_args)
    assert replaced
    assert code == 2 and images[0].name in err and "changed while fullview was reading" in err, err
    lines = [line for line in err.split("\n") if line.strip() and "\r" not in line]  # progress bars redraw with \r
    assert len(lines) == 1 and lines[0].startswith("fullview: error:") and "Traceback" not in err, err
    assert not (ws / "tiny" / "features" / "manifest.json").exists()  # no result filed under either file's hash
    monkeypatch.undo()
    assert _cli(capsys, "run", dataset_copy, "-w", ws, "--until", "features", *tiny_set_args)[0] == 0
    assert _status(capsys, dataset_copy, ws, tiny_set_args)["features"][0] == "fresh"


def test_5_an_image_rewritten_in_place_during_a_run_is_caught_at_its_decode(dataset_copy, tmp_path, monkeypatch):
    """The decode checks the file is still the one validated and hashed (same inode, size, mtime, ctime)."""
    from fullview.io.dataset import Dataset, DatasetError

    ds = Dataset(dataset_copy)
    ds.validate_inputs()
    name = ds.image_names[0]
    ds.image_hash(name)
    path = ds.image_path(name)
    data = path.read_bytes()
    # (past the kernel's coarse clock tick, which stamps change times: within one tick a rewrite cannot be seen)
    _wait_for(lambda: time.time_ns() > path.stat().st_ctime_ns + 50_000_000, "the clock to move on", 5)
    with open(path, "r+b") as f:  # the same bytes written again: the same inode, a new change time
        f.write(data)
    with pytest.raises(DatasetError, match="changed while fullview was reading"):
        ds.load_image(name, width=256)
    ds.refresh_inputs()  # a long-lived reader that expects the change takes the file as it is now
    assert ds.load_image(name, width=256).shape == (128, 256, 3)


# ------------------------------------------------------------------------------- 7. COLMAP text names read back
def _one_image_model(names: list[str]):
    from fullview.io.exports import SparseModel

    n = len(names)
    R = np.tile(np.eye(3), (n, 1, 1))
    t = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    return SparseModel(image_names=names, image_sizes=[(64, 32)] * n, registered=np.ones(n, bool),
                       R_cam_from_world=R, t_cam_from_world=t, points=np.array([[0.0, 0.0, 5.0]]),
                       colors=np.array([[10, 20, 30]], np.uint8), point_errors_rad=np.array([0.001]),
                       track_point3d=np.zeros(n, np.int64), track_image=np.arange(n),
                       track_point2d=np.zeros(n, np.int64), pixels=[np.array([[32.0, 16.0]])] * n)


def _names_read_back(folder: Path) -> list[str]:
    import pycolmap

    rec = pycolmap.Reconstruction(folder)
    return [rec.images[k].name for k in sorted(rec.images)]


@pytest.mark.parametrize("name", ["pano é 0.png", "a\tb.png", "trail .png", "a\nb.png", "a\rb.png", "a\x1fb.png"])
def test_7_colmap_text_refuses_a_name_it_would_not_read_back(tmp_path, name):
    from fullview.io.exports import ExportError, write_colmap_model

    model = _one_image_model([name, "pano_1.png"])
    with pytest.raises(ExportError, match="colmap-bin") as info:
        write_colmap_model(model, tmp_path / "text", binary=False)
    assert repr(name) in str(info.value) and "\n" not in str(info.value)
    assert not list((tmp_path / "text").glob("*.txt"))  # nothing half written
    write_colmap_model(model, tmp_path / "bin", binary=True)
    assert _names_read_back(tmp_path / "bin") == [name, "pano_1.png"]  # the binary format keeps it exactly


@pytest.mark.parametrize("name", ["pano_ü_é.png", "a\u00a0b.png", "日本.jpg", "#1.png"])
def test_7_colmap_text_keeps_other_names_exactly(tmp_path, name):
    from fullview.io.exports import write_colmap_model

    write_colmap_model(_one_image_model([name, "pano_1.png"]), tmp_path, binary=False)
    assert _names_read_back(tmp_path) == [name, "pano_1.png"]


def test_7_a_dataset_with_a_space_in_a_name_runs_and_exports_binary_not_text(tiny_dataset, tmp_path, tiny_set_args,
                                                                            capsys):
    data = tmp_path / "spaced"
    shutil.copytree(tiny_dataset, data)
    (data / "images" / "pano_000.png").rename(data / "images" / "pano é 0.png")
    hand = data / "hand_points.yaml"
    hand.write_text(hand.read_text().replace("pano_000.png", "pano é 0.png"))
    ws = tmp_path / "ws"
    assert _cli(capsys, "run", data, "-w", ws, "--until", "triangulation", *tiny_set_args)[0] == 0
    model_dir = ws / "spaced" / "triangulation" / "models" / "0"  # the stage's own model: binary for this name
    assert "pano é 0.png" in _names_read_back(model_dir)
    code, _, err = _cli(capsys, "export", data, "-w", ws, "--format", "colmap", *tiny_set_args)
    assert code == 2 and "'pano é 0.png'" in err and "--format colmap-bin" in err and len(err.strip().splitlines()) == 1
    code, out, err = _cli(capsys, "export", data, "-w", ws, "--format", "colmap-bin", *tiny_set_args)
    assert code == 0, err
    assert "pano é 0.png" in _names_read_back(Path(out.strip()) / "0")


# ------------------------------------------------------------------- 6. an export removes only what it wrote itself
def _export(dataset, ws, settings, fmt, out, *extra) -> int:
    return main(["export", str(dataset), "-w", str(ws), "--format", fmt, *settings, "--out", str(out), *extra])


def _listed_files_are_there(out: Path) -> dict:
    from fullview.io.workspace import file_sha256

    manifest = json.loads((out / "manifest.json").read_text())
    assert "pending" not in manifest
    for rel, entry in manifest["outputs"].items():
        assert file_sha256(out / rel) == entry["sha256"], rel
    return manifest


def test_6_reexport_keeps_the_users_files_and_is_complete(tiny_dataset, sparse_ws, tmp_path, tiny_set_args):
    out = tmp_path / "X"
    assert _export(tiny_dataset, sparse_ws, tiny_set_args, "colmap", out) == 0
    (out / "notes.txt").write_text("my notes")
    (out / "0" / "mine").mkdir()
    (out / "0" / "mine" / "keep.txt").write_text("keep me")
    first = _listed_files_are_there(out)
    assert _export(tiny_dataset, sparse_ws, tiny_set_args, "colmap", out) == 0
    assert (out / "notes.txt").read_text() == "my notes" and (out / "0" / "mine" / "keep.txt").read_text() == "keep me"
    assert _listed_files_are_there(out)["outputs"] == first["outputs"]
    assert len(_names_read_back(out / "0")) > 0
    # another format into the same folder: the earlier export's files go, the user's stay
    assert _export(tiny_dataset, sparse_ws, tiny_set_args, "colmap-bin", out) == 0
    assert not list(out.glob("*/*.txt")) and (out / "0" / "images.bin").exists()
    assert (out / "notes.txt").exists() and (out / "0" / "mine" / "keep.txt").exists()
    assert set(_listed_files_are_there(out)["outputs"]) == {str(p.relative_to(out)) for p in out.rglob("*.bin")} | {
        "README.txt"}  # the export's own note of what it holds and its unit


@pytest.mark.parametrize("intrusion", ["changed", "foreign_in_the_way", "symlinked_folder"])
def test_6_an_export_that_would_overwrite_a_file_not_its_own_is_refused(tiny_dataset, sparse_ws, tmp_path,
                                                                        tiny_set_args, capsys, intrusion):
    out = tmp_path / "X"
    assert _export(tiny_dataset, sparse_ws, tiny_set_args, "colmap", out) == 0
    elsewhere = tmp_path / "elsewhere"
    if intrusion == "changed":  # the user edited a file of the export: it is theirs now
        victim, fmt = out / "0" / "cameras.txt", "colmap"
        victim.write_text(victim.read_text() + "# my edit\n")
    elif intrusion == "foreign_in_the_way":  # a file of the user's where the binary export would write
        victim, fmt = out / "0" / "cameras.bin", "colmap-bin"
        victim.write_bytes(b"mine")
    else:  # the model folder is a link to a folder of the user's
        (out / "0").rename(elsewhere)
        (out / "0").symlink_to(elsewhere)
        victim, fmt = elsewhere / "cameras.txt", "colmap"
    kept = victim.read_bytes()
    capsys.readouterr()
    assert _export(tiny_dataset, sparse_ws, tiny_set_args, fmt, out) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "export again" in err, err
    assert victim.read_bytes() == kept


@pytest.mark.parametrize("cuts", [1, 2])
def test_6_an_export_cut_short_is_finished_by_the_next(tiny_dataset, sparse_ws, tmp_path, tiny_set_args, monkeypatch,
                                                       cuts):
    """Cut between two files (as a kill would), once or twice in a row with other formats: the record keeps every
    file an export of its own wrote, so the next export replaces them all and keeps the user's."""
    from fullview.io import workspace

    out = tmp_path / "X"
    assert _export(tiny_dataset, sparse_ws, tiny_set_args, "colmap", out) == 0
    (out / "notes.txt").write_text("my notes")
    real_replace = os.replace
    for fmt in ["colmap-bin", "nerfstudio"][:cuts]:
        moved = []

        def cut_short(src, dst):
            if str(dst).startswith(f"{out}{os.sep}") and Path(dst).name != "manifest.json":  # a file moved into X
                if len(moved) == 1:
                    raise KeyboardInterrupt  # as a kill between two files would leave it
                moved.append(dst)
            real_replace(src, dst)
        monkeypatch.setattr(workspace.os, "replace", cut_short)
        assert _export(tiny_dataset, sparse_ws, tiny_set_args, fmt, out) != 0
        monkeypatch.undo()
        assert len(moved) == 1  # one of the new files is in, the others not
        assert "pending" in json.loads((out / "manifest.json").read_text())
    assert _export(tiny_dataset, sparse_ws, tiny_set_args, "colmap", out) == 0
    manifest = _listed_files_are_there(out)
    on_disk = {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()} - {"manifest.json", "notes.txt"}
    assert on_disk == set(manifest["outputs"])  # nothing of the cut exports is left
    assert (out / "notes.txt").read_text() == "my notes"
    assert not list(tmp_path.glob(".X.running.*"))


# ------------------------------------------------------------ 13. a PLY export says when the dense cloud is not current
def test_13_ply_export_with_densify_stale_or_missing_exits_2_unless_sparse_only(tiny_dataset, sparse_ws, dense_ws,
                                                                               tmp_path, tiny_set_args, capsys):
    settings = [*tiny_set_args, *DENSE]
    assert _export(tiny_dataset, dense_ws, settings, "ply", tmp_path / "fresh") == 0
    assert (tmp_path / "fresh" / "0" / "dense.ply").exists() and (tmp_path / "fresh" / "0" / "sparse.ply").exists()
    capsys.readouterr()
    stale = [*settings, "--set", "densify.min_pair_inliers=31"]
    assert _export(tiny_dataset, dense_ws, stale, "ply", tmp_path / "stale") == 2
    err = capsys.readouterr().err
    assert "densify is stale" in err and "densify.min_pair_inliers" in err and "--sparse-only" in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "stale").exists()
    assert _export(tiny_dataset, sparse_ws, tiny_set_args, "ply", tmp_path / "never") == 2
    assert "densify has not run" in capsys.readouterr().err
    assert _export(tiny_dataset, dense_ws, stale, "ply", tmp_path / "sparse", "--sparse-only") == 0
    assert sorted(p.name for p in (tmp_path / "sparse").rglob("*.ply")) == ["sparse.ply"]
