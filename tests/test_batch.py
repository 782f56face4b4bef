"""fullview batch: three datasets on a LocalCluster of two worker processes, one worker killed (SIGKILL) while a
stage runs; every artifact must be byte-identical to a serial run, and a broken dataset fails alone."""

from __future__ import annotations

import os
import signal
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from fullview.cli import main
from fullview.commands.batch import cluster_client
from fullview.io.config import load_config
from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace
from fullview.stages import PIPELINE
from fullview.stages.batch import run_batch, summary_table
from fullview.stages.runner import Pipeline
from fullview.synth import write_synthetic_dataset

UNTIL = "triangulation"  # densify is the slow stage; everything before it is exercised
KILL_STAGE = "features"  # a stage that fans out: its task and its per-image subtasks run on both workers
FAST = ["features.max_features_per_face=200", "features.min_features_per_face=0"]  # fewer features, same code
TIMEOUT_S = 150  # the whole batch, cluster start and stop included; a hang fails instead of blocking CI


@contextmanager
def _deadline(seconds: int):
    def expire(*_):
        raise TimeoutError(f"batch test exceeded {seconds} s")
    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def _outputs(ws_root: Path, name: str) -> dict[str, dict]:
    """Per stage: fingerprint and every output's size and sha256, from the manifests."""
    ws = Workspace(ws_root, name)
    return {s: {"fingerprint": m["fingerprint"], "outputs": m["outputs"]}
            for s in PIPELINE[:PIPELINE.index(UNTIL) + 1] if (m := ws.read_manifest(s)) is not None}


def _kill_worker_during_stage(client, ws_root: Path, names: list[str], pids: dict[str, int], found: dict,
                              stop: threading.Event) -> None:
    """Once a dataset's KILL_STAGE has written its first artifact into its temporary folder, SIGKILL the worker
    process that runs that dataset's stage task."""
    while not stop.is_set():
        for name in names:
            running = [p for p in (ws_root / name).glob(f".{KILL_STAGE}.running.*") if any(p.glob("*.npz"))]
            if not running:
                continue
            for address, keys in client.processing().items():
                if any(str(k).startswith(f"fullview-{KILL_STAGE}-{name}-") for k in keys):
                    os.kill(pids[address], signal.SIGKILL)
                    found.update(dataset=name, worker=address, pid=pids[address], temporary=running[0])
                    return
        time.sleep(0.005)


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("batch_data")
    good = [write_synthetic_dataset(root / f"room{s}", views=4, width=512, seed=s) for s in (1, 2, 3)]
    broken = write_synthetic_dataset(root / "broken", views=2, width=128, seed=4)
    sorted((broken / "images").iterdir())[0].write_bytes(b"not an image")
    return [*good, broken]


def test_batch_survives_a_killed_worker_with_the_serial_run_bytes(datasets, tmp_path, tiny_set_args):
    config = load_config(None, [*tiny_set_args[1::2], *FAST])
    good, broken = datasets[:3], datasets[3]
    for path in good:  # the reference: serial runs, local threads
        ds = Dataset(path)
        Pipeline(ds, Workspace(tmp_path / "serial", ds.name), config).run(until=UNTIL)

    found: dict = {}
    stop = threading.Event()
    with _deadline(TIMEOUT_S), cluster_client(None, 2) as client:
        assert all(a.startswith("tcp://127.0.0.1:") for a in client.scheduler_info()["workers"])
        pids = client.run(os.getpid)
        assert len(pids) == 2 and os.getpid() not in pids.values()  # two worker processes, not threads
        watcher = threading.Thread(target=_kill_worker_during_stage,
                                   args=(client, tmp_path / "batch", [p.name for p in good], pids, found, stop),
                                   daemon=True)
        watcher.start()
        try:
            outcomes = run_batch([Dataset(p) for p in datasets], config, tmp_path / "batch", client, until=UNTIL,
                                 progress=False)
        finally:
            stop.set()
            watcher.join(5)
        alive = client.run(os.getpid)
    print(summary_table(outcomes))

    assert found, f"no worker was killed during {KILL_STAGE}"
    assert found["pid"] not in alive.values()  # the killed process is gone; its nanny started a new one
    by_name = {o.name: o for o in outcomes}
    assert by_name["broken"].status == "failed" and "features" in by_name["broken"].reason
    assert "cannot read image" in by_name["broken"].reason  # one line naming the file, not a traceback
    for path in good:
        outcome = by_name[path.name]
        assert outcome.status == "ok", outcome.reason
        expected = list(PIPELINE[:PIPELINE.index(UNTIL) + 1])
        if path.name == found["dataset"] and KILL_STAGE not in outcome.ran:
            expected.remove(KILL_STAGE)  # killed just after its swap: committed, so its rerun found it fresh
        assert outcome.ran == expected
        assert outcome.registered == 4 and outcome.points > 100
        # The stage task that died held the workspace lock: its retry could take it (an fcntl lock dies with its
        # process), and every artifact is the serial run's, byte for byte (manifest sha256 and fingerprints).
        assert _outputs(tmp_path / "batch", path.name) == _outputs(tmp_path / "serial", path.name)
        # A committed folder holds its manifest's outputs and nothing else (no partial file of a killed task).
        for stage in PIPELINE[:PIPELINE.index(UNTIL) + 1]:
            folder = tmp_path / "batch" / path.name / stage
            on_disk = {str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()}
            assert on_disk == {*Workspace(tmp_path / "batch", path.name).read_manifest(stage)["outputs"],
                               "manifest.json"}


def test_batch_bad_input_is_one_line(datasets, tmp_path, capsys):
    def run(*args):
        code = main(["batch", *map(str, args), "-w", str(tmp_path / "ws")])
        err = capsys.readouterr().err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        return code, err

    code, err = run(tmp_path / "nope")
    assert code == 2 and "dataset folder not found" in err and "nope" in err
    code, err = run("--glob", str(tmp_path / "none*"))
    assert code == 2 and "matches no folder" in err
    code, err = run()
    assert code == 2 and "no datasets given" in err
    twin = tmp_path / "elsewhere" / datasets[0].name
    (twin / "images").mkdir(parents=True)
    for image in sorted((datasets[0] / "images").iterdir()):
        (twin / "images" / image.name).symlink_to(image)
    code, err = run(datasets[0], twin)
    assert code == 2 and "same folder name" in err and datasets[0].name in err
    code, err = run(datasets[0], datasets[0])
    assert code == 2 and "given twice" in err
    code, err = run(datasets[0], "--workers", "0")
    assert code == 2 and "at least one worker" in err
    code, err = run(datasets[0], "--workers", "2", "--scheduler", "tcp://127.0.0.1:8786")
    assert code == 2 and "cannot be combined with --scheduler" in err
    assert not (tmp_path / "ws").exists()  # refused before any cluster or workspace
