"""Hostile inputs (issue 30, items 9, 11, 12, 13): every input is bounded where it is read, and bad input of every
kind is exit code 2 with one line naming the file, key or value, never a traceback or an "internal error".

9 image headers against the pixel budget and the data they hold; 11 settings whose bounds crashed (cross-key rules,
no surviving point, face size and memory) and batch workers' tracebacks; 12 YAML 1.2 scalars in the config, `--set`
and hand points; 13 messages for masks, dangling links, hand-point names, NaN and a full disk. Then property tests
(Hypothesis) on image headers and on `--set` values.
"""

from __future__ import annotations

import errno
import io
import math
import re
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import PIL.Image
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import fullview.io.limits as limits
from fullview.cli import main
from fullview.io.config import ConfigError, load_config
from fullview.io.dataset import Dataset, DatasetError, image_size
from fullview.io.yamlio import load_yaml
from fullview.sfm.bundle import _build_layout, _median_depths, _pack, _Problem
from fullview.sfm.camera import normalize, tangent_basis
from fullview.sfm.features import detect_features, noise_sigma
from fullview.sfm.options import OPTIONS_BY_SECTION, FeaturesOptions, option_fields

# No example database: it would be written into the shared working tree.
PROPERTY = settings(max_examples=120, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


# ------------------------------------------------------------------------------------------------ helpers
def _jpeg(w: int = 64, h: int = 32, seed: int = 0) -> bytes:
    image = np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)
    out = io.BytesIO()
    PIL.Image.fromarray(image).save(out, "JPEG")
    return out.getvalue()


def _forged_jpeg(w: int, h: int) -> bytes:
    """A small flat JPEG whose frame header (SOF0) claims w x h."""
    out = io.BytesIO()
    PIL.Image.fromarray(np.full((8, 16), 128, np.uint8)).save(out, "JPEG")
    data = bytearray(out.getvalue())
    sof = data.find(b"\xff\xc0")
    struct.pack_into(">HH", data, sof + 5, h, w)
    return bytes(data)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _forged_png(w: int, h: int, idat: bytes | None = None) -> bytes:
    """A PNG (8-bit grey) whose IHDR claims w x h, with a valid but short IDAT (100 bytes by default)."""
    if idat is None:  # a complete zlib stream of 89 stored bytes: 100 bytes, the structure fine, the data short
        idat = zlib.compress(np.random.default_rng(0).integers(0, 256, 89, dtype=np.uint8).tobytes(), 0)
        assert len(idat) == 100
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def _cli(capsys, *args) -> tuple[int, str]:
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


# A log record of the run's progress ("01:19:35 settings recorded in ..."); warnings and errors name their level.
_INFO = re.compile(r"^\d\d:\d\d:\d\d (?!warning: |error: )")
_ERROR = re.compile(r"^\d\d:\d\d:\d\d error: (.*)$")


def _one_error(code: int, err: str, *names: str, alone: bool = True) -> str:
    """The single "fullview: error:" line of a refused command (exit 2), naming every one of `names`; with `alone`,
    the only line on stderr besides INFO records (no warning, no C library's message, no progress bar)."""
    assert code == 2, err
    assert "Traceback" not in err and "internal error" not in err, err
    lines = [line for line in err.splitlines() if "fullview: error:" in line]
    assert len(lines) == 1, err
    if alone:
        assert [line for line in err.strip().splitlines() if not _INFO.match(line)] == lines, err
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


def _subprocess_cli(*args) -> tuple[int, str]:
    """The CLI in a process of its own: its real stderr (warnings and C libraries' messages included)."""
    proc = subprocess.run([sys.executable, "-m", "fullview", *map(str, args)], capture_output=True, text=True,
                          timeout=120)
    return proc.returncode, proc.stderr


def _stage_ran(ws: Path, stage: str) -> bool:
    return any(ws.rglob(f"{stage}")) or any(ws.rglob(f".{stage}.*"))


# ------------------------------------------------------------------- 9 image headers against data and budget
def test_jpeg_header_claiming_16384x8192_is_refused_by_name(dataset_copy, tmp_path):
    bad = dataset_copy / "images" / "pano_000.png"
    data = _forged_jpeg(16384, 8192)
    assert len(data) < 700
    bad.write_bytes(data)
    for extra in ([], ["--set", "features.working_width=0"]):
        code, err = _subprocess_cli("run", dataset_copy, "-w", tmp_path / "ws", "--until", "features", *extra)
        line = _one_error(code, err, "pano_000.png", "16384x8192")
        assert "MemoryError" not in err and "DecompressionBomb" not in err, line
    assert not _stage_ran(tmp_path / "ws", "features")


def test_png_header_claiming_16384x8192_with_a_100_byte_idat_is_refused(dataset_copy, tmp_path):
    bad = dataset_copy / "images" / "pano_001.png"
    bad.write_bytes(_forged_png(16384, 8192))
    code, err = _subprocess_cli("run", dataset_copy, "-w", tmp_path / "ws", "--until", "features")
    _one_error(code, err, "pano_001.png", "16384x8192")
    assert "libpng" not in err and "DecompressionBomb" not in err
    assert not _stage_ran(tmp_path / "ws", "features")


@pytest.mark.parametrize("make", [_forged_jpeg, _forged_png], ids=["jpeg", "png"])
def test_header_lies_within_the_budget_are_refused_by_their_data(tmp_path, make):
    path = tmp_path / "lie.png"
    path.write_bytes(make(4096, 2048))  # 8 Mpx: inside any machine's budget, but the data holds a few bytes
    with pytest.raises(DatasetError, match=r"lie.png: its header claims 4096x2048 pixels but"):
        image_size(path)


def test_pixel_budget_follows_the_machine_memory(tmp_path, monkeypatch):
    path = tmp_path / "pano.jpg"
    path.write_bytes(_jpeg(512, 256))
    assert image_size(path) == (512, 256)
    # A machine whose half memory holds the features of two 100k-pixel panoramas, not two of 131k.
    memory = 2 * limits.FEATURES_IMAGES_AT_ONCE * limits.FEATURES_BYTES_PER_PIXEL * 100_000
    monkeypatch.setattr(limits, "machine_memory", lambda: memory)
    assert abs(limits.pixel_budget() - 100_000) <= 1
    with pytest.raises(DatasetError, match=r"pano.jpg is 512x256 \(0.1 Mpx\), more than this machine's budget"):
        image_size(path)


def test_pixel_budget_is_within_half_the_memory_and_pil_limit():
    budget = limits.pixel_budget()
    assert budget <= PIL.Image.MAX_IMAGE_PIXELS
    assert budget * limits.FEATURES_BYTES_PER_PIXEL * limits.FEATURES_IMAGES_AT_ONCE <= 0.5 * limits.machine_memory()


def test_two_by_one_images_are_refused_by_name(dataset_copy, tmp_path, capsys):
    for name in ("pano_000.png", "pano_001.png", "pano_002.png"):
        cv2.imwrite(str(dataset_copy / "images" / name), np.full((1, 2, 3), 90, np.uint8))
    code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws", "--until", "features")
    _one_error(code, err, "pano_000.png", "2x1", "at least 3 pixels high")


def test_the_smallest_accepted_image_gives_features_without_error():
    assert 0.0 <= noise_sigma(np.zeros((3, 6), np.uint8)) < 0.1  # (the median is interpolated within its bin)
    features = detect_features(np.random.default_rng(0).integers(0, 256, (3, 6, 3), np.uint8), FeaturesOptions())
    assert len(features.bearings) == 0
    with pytest.raises(ValueError, match="no pixel with a full 3x3 neighbourhood"):
        noise_sigma(np.zeros((1, 2), np.uint8))


# ----------------------------------------------------------------------- 11 settings that crashed, batch
def test_retrieval_rule_names_both_keys(dataset_copy, tmp_path, capsys):
    code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws", "--set", "matches.pairs=retrieval",
                     "--set", "matches.retrieval_neighbours=0")
    _one_error(code, err, "matches.retrieval_neighbours=0", "matches.pairs='retrieval'")


def test_no_surviving_point_is_a_clean_error(dataset_copy, tmp_path, capsys, tiny_set_args):
    code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws", "--until", "triangulation",
                     *tiny_set_args, "--set", "triangulation.min_triangulation_angle_deg=89.9")
    _one_error(code, err, "no point survives triangulation.min_triangulation_angle_deg=89.9", alone=False)


def test_median_depths_of_cameras_without_observations():
    """The last cameras observing nothing (their tracks filtered away) get an infinite depth, not an IndexError."""
    R = np.repeat(np.eye(3)[None], 3, axis=0)
    C = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    t = -np.einsum("nij,nj->ni", R, C)
    points = np.array([[0.0, 0, 5], [1, 1, 4]])
    cam, pt = np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1])
    bearings = normalize(points[pt] - C[cam])
    layout = _build_layout(C, len(points), np.array([0]), None, cam)
    problem = _Problem(R_init=R, t_init=t, C_init=C, obs_camera=cam, obs_point=pt, bearings=bearings,
                       basis=tangent_basis(bearings), layout=layout)
    depth = _median_depths(_pack(layout, C, points), problem)
    assert depth[2] == np.inf and np.isfinite(depth[:2]).all()
    assert depth[0] == pytest.approx(5.0)  # the upper of its two distances (5 and 4.24): index count // 2


def test_face_size_is_bounded_by_memory(dataset_copy, monkeypatch, capsys, tmp_path):
    code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws", "--set", "features.face_size=16384")
    _one_error(code, err, "features.face_size", "16384")
    # A 4 GiB machine cannot hold 4096-px faces for two images (2 x 290 B x 4096² = 9 GiB); it holds 1924-px ones.
    monkeypatch.setattr(limits, "machine_memory", lambda: 4 * 2**30)
    with pytest.raises(ConfigError, match=r"features.face_size=4096 needs about 9 GiB .* at most 1924 fits"):
        load_config(None, ["features.face_size=4096"])
    assert load_config(None, ["features.face_size=1924"])["features"].face_size == 1924
    # The static bound: the native face (margin 5) of the widest panorama PIL's limit admits is below it.
    widest = math.isqrt(2 * PIL.Image.MAX_IMAGE_PIXELS)
    assert round(widest * 100 / 360) <= OPTIONS_BY_SECTION["features"].__dataclass_fields__["face_size"].metadata["le"]


def test_batch_reports_one_line_per_failing_dataset(tmp_path):
    for name, data in (("tiny", None), ("forged", _forged_png(4096, 2048))):
        images = tmp_path / name / "images"
        images.mkdir(parents=True)
        for k in range(9):
            if data is None:
                cv2.imwrite(str(images / f"p{k}.png"), np.full((1, 2, 3), 90 + k, np.uint8))
            else:
                (images / f"p{k}.png").write_bytes(data)
    code, err = _subprocess_cli("batch", tmp_path / "tiny", tmp_path / "forged", "-w", tmp_path / "ws",
                                "--workers", "1")
    assert code == 1, err
    assert "Traceback" not in err and "Compute Failed" not in err, err
    errors = sorted(m.group(1) for line in err.splitlines() if (m := _ERROR.match(line)))
    assert len(errors) == 2, err
    assert errors[0].startswith("forged: features: ") and "4096x2048" in errors[0]
    assert errors[1].startswith("tiny: features: ") and "2x1" in errors[1]


def _raise_in_a_task(plugin: bool) -> None:
    from fullview.commands.batch import cluster_client
    from fullview.stages.batch import WorkerLogging
    with cluster_client(None, 1) as client:
        if plugin:
            client.register_plugin(WorkerLogging(), name="fullview-logging")
        with pytest.raises(ZeroDivisionError):
            client.submit(lambda: 1 // 0, pure=False).result()


_TASK_SCRIPT = """
import sys
sys.path.insert(0, {here!r})
from test_hostile_inputs import _raise_in_a_task
if __name__ == "__main__":
    _raise_in_a_task(sys.argv[1] == "1")
"""


def test_worker_does_not_print_a_failed_tasks_traceback(tmp_path):
    script = tmp_path / "task.py"  # a file: the cluster's worker processes re-import the main module
    script.write_text(_TASK_SCRIPT.format(here=str(Path(__file__).parent)))
    stderr = {}
    for plugin in (False, True):
        proc = subprocess.run([sys.executable, str(script), str(int(plugin))], capture_output=True, text=True,
                              timeout=120)
        assert proc.returncode == 0, proc.stderr
        stderr[plugin] = proc.stderr
    assert "Compute Failed" in stderr[False]  # what the plugin removes: distributed's record with the traceback
    assert "Compute Failed" not in stderr[True] and "Traceback" not in stderr[True], stderr[True]


# ------------------------------------------------------------------------------------------ 12 YAML 1.2
@pytest.mark.parametrize("text, value", [("010", 10), ("0o17", 15), ("0x1F", 31), ("1e-3", 1e-3), ("1e3", 1000.0),
                                         ("1:30", "1:30"), ("yes", "yes"), ("no", "no"), ("on", "on"),
                                         ("off", "off"), ("true", True), ("FALSE", False), ("~", None),
                                         ("2024-01-02", "2024-01-02"), ("1_000", "1_000"), (".inf", math.inf)])
def test_yaml_scalars_follow_the_1_2_core_schema(text, value):
    assert load_yaml(text, "x") == value and type(load_yaml(text, "x")) is type(value)


def test_set_values_follow_yaml_1_2(dataset_copy, capsys, tmp_path):
    config = load_config(None, ["matches.window=010", "filter.threshold_deg=1e-3", "densify.outlier_std_ratio=1e3"])
    assert config["matches"].window == 10
    assert config["filter"].threshold_deg == 1e-3 and config["densify"].outlier_std_ratio == 1000.0
    for item, names in (("matches.window=1:30", ("matches.window", "'1:30'")),
                        ("features.root_sift=yes", ("features.root_sift", "'yes'")),
                        ("features.root_sift=off", ("features.root_sift", "'off'"))):
        code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws", "--set", item)
        _one_error(code, err, *names)


def test_config_file_follows_yaml_1_2(tmp_path):
    path = tmp_path / "pipeline.yaml"
    path.write_text("matches:\n  window: 010\nfilter:\n  threshold_deg: 1e-1\n")
    config = load_config(path)
    assert config["matches"].window == 10 and config["filter"].threshold_deg == 0.1
    path.write_text("matches:\n  mutual: on\n")
    with pytest.raises(ConfigError, match=r"pipeline.yaml: matches.mutual must be bool, got 'on'"):
        load_config(path)


def _hand_points(root: Path, text: str) -> None:
    (root / "hand_points.yaml").write_text(text)


def test_hand_points_follow_yaml_1_2(dataset_copy):
    _hand_points(dataset_copy, "points:\n  - observations: {pano_000.png: [010, 020], pano_001.png: [1e1, 2]}\n")
    track = Dataset(dataset_copy).hand_tracks()[0]
    assert track.observations == {"pano_000.png": (10.0, 20.0), "pano_001.png": (10.0, 2.0)}
    _hand_points(dataset_copy, "points:\n  - observations: {pano_000.png: [1:30, 20], pano_001.png: [1, 2]}\n")
    with pytest.raises(DatasetError, match=r"point 'point_0' in pano_000.png: expected \[x, y\] of two finite "
                                           r"numbers, got \['1:30', 20\]"):
        Dataset(dataset_copy).hand_tracks()


def test_hand_points_top_level_key_is_named(dataset_copy, tmp_path, capsys):
    _hand_points(dataset_copy, "version: 2\npoints:\n  - observations: {pano_000.png: [1, 2], pano_001.png: [3, 4]}\n")
    code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws")
    _one_error(code, err, "hand_points.yaml", "unknown top-level key 'version'")


def test_saved_hand_point_names_read_back_as_written(dataset_copy):
    """Names YAML 1.1 or 1.2 would read as numbers, booleans or dates are quoted when the picker saves them."""
    names = ["1e3", "010", "yes", "1:30", "2024-01-02", "null", "corner"]
    ds = Dataset(dataset_copy)
    ds.save_hand_points([{"name": n, "observations": {"pano_000.png": [1 + k, 2], "pano_001.png": [3, 4]}}
                         for k, n in enumerate(names)])
    assert [t.name for t in Dataset(dataset_copy).hand_tracks()] == names


# ------------------------------------------------------------------------------------ 13 clear messages
def _write_masks(root: Path, value: int, names=("pano_000.png",)) -> None:
    (root / "masks").mkdir(exist_ok=True)
    for name in names:
        cv2.imwrite(str(root / "masks" / f"{name}.png"), np.full((256, 512), value, np.uint8))


def test_all_black_mask_fails_at_validation(dataset_copy, tmp_path, capsys):
    _write_masks(dataset_copy, 0)
    code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws")
    _one_error(code, err, "masks/pano_000.png.png", "keeps no pixel")
    assert not _stage_ran(tmp_path / "ws", "features")
    _write_masks(dataset_copy, 255)  # white keeps every pixel: accepted
    Dataset(dataset_copy).validate_inputs()


def test_forged_mask_is_refused_before_decoding(dataset_copy):
    (dataset_copy / "masks").mkdir()
    (dataset_copy / "masks" / "pano_000.png.png").write_bytes(_forged_png(512, 256))
    with pytest.raises(DatasetError, match=r"mask .*pano_000.png.png: its header claims 512x256"):
        Dataset(dataset_copy).validate_inputs()


def test_masks_that_is_a_file_is_an_error(dataset_copy, tmp_path, capsys):
    (dataset_copy / "masks").write_text("not a folder")
    code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws")
    _one_error(code, err, "masks", "not a folder")
    (dataset_copy / "masks").unlink()
    (dataset_copy / "masks").symlink_to(tmp_path / "gone")
    code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws")
    _one_error(code, err, "masks", "broken symbolic link")


def test_dangling_workspace_symlink_is_named(dataset_copy, tmp_path, capsys):
    link = tmp_path / "ws"
    link.symlink_to(tmp_path / "nowhere")
    for ws in (link, link / "sub"):
        code, err = _cli(capsys, "run", dataset_copy, "-w", ws, "--until", "features")
        _one_error(code, err, str(link), "dangling symbolic link")


def test_unnamed_point_beside_one_named_point_0(dataset_copy):
    _hand_points(dataset_copy, "points:\n"
                               "  - observations: {pano_000.png: [1, 2], pano_001.png: [3, 4]}\n"
                               "  - name: point_0\n    observations: {pano_000.png: [5, 6], pano_002.png: [7, 8]}\n")
    names = [t.name for t in Dataset(dataset_copy).hand_tracks()]
    assert len(set(names)) == 2 and "point_0" in names
    _hand_points(dataset_copy, "points:\n"
                               "  - {name: a, observations: {pano_000.png: [1, 2], pano_001.png: [3, 4]}}\n"
                               "  - {name: a, observations: {pano_000.png: [5, 6], pano_002.png: [7, 8]}}\n")
    with pytest.raises(DatasetError, match="point name 'a' is used twice"):  # a user's own duplicate still is one
        Dataset(dataset_copy).hand_tracks()


@pytest.mark.parametrize("value", [".nan", ".NaN", "nan", ".inf"])
def test_nan_hand_point_is_refused_at_load(dataset_copy, tmp_path, capsys, value):
    _hand_points(dataset_copy, f"points:\n  - observations: {{pano_000.png: [{value}, 2], pano_001.png: [3, 4]}}\n")
    code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws")
    _one_error(code, err, "hand_points.yaml", "point_0", "pano_000.png", "two finite numbers")


def test_disk_full_names_the_file_and_the_stage(dataset_copy, tmp_path, capsys, monkeypatch, tiny_set_args):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(np, "savez", full)
    code, err = _cli(capsys, "run", dataset_copy, "-w", tmp_path / "ws", "--until", "features", *tiny_set_args)
    line = _one_error(code, err, "No space left on device", "features stage", alone=False)
    assert ".npz" in line and ".features." in line
    assert not (tmp_path / "ws" / "tiny" / "features").exists()


# ------------------------------------------------------------------------------------------ properties
_FORMATS = st.sampled_from(["jpeg", "png"])


@PROPERTY
@given(fmt=_FORMATS, width=st.integers(0, 40_000), height=st.integers(0, 20_000), cut=st.integers(0, 4000),
       forge=st.booleans(), truncate=st.booleans())
def test_image_headers_are_accepted_only_when_decodable(tmp_path, fmt, width, height, cut, forge, truncate):
    """Random header sizes and truncations of real JPEG and PNG files: validation accepts exactly what decodes
    whole to the size it reports, else a DatasetError; never another exception."""
    if fmt == "jpeg":
        data = bytearray(_jpeg(64, 32))
        if forge:
            sof = data.find(b"\xff\xc0")
            struct.pack_into(">HH", data, sof + 5, min(height, 65535), min(width, 65535))
    else:
        buf = io.BytesIO()
        PIL.Image.fromarray(np.random.default_rng(1).integers(0, 256, (32, 64, 3), np.uint8)).save(buf, "PNG")
        data = bytearray(buf.getvalue())
        if forge:
            struct.pack_into(">II", data, 16, width, height)
            data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])) & 0xFFFFFFFF)
    if truncate:
        data = data[:cut]
    path = tmp_path / f"x.{fmt}"
    path.write_bytes(bytes(data))
    try:
        w, h = image_size(path)
    except DatasetError as e:
        assert "\n" not in str(e) and "x." in str(e)
        return
    with PIL.Image.open(path) as im:
        im.load()  # raises on data that ends early (PIL does not load truncated images by default)
        assert im.size == (w, h)
    assert w * h <= limits.pixel_budget() and w == 2 * h


_KEYS = [(section, f) for section, cls in OPTIONS_BY_SECTION.items() for f in option_fields(cls)]
_VALUE_TEXT = st.one_of(
    st.sampled_from(["010", "0o10", "0x10", "1:30", "1e3", "1e-3", "-1e400", ".nan", ".inf", "yes", "no", "on",
                     "off", "true", "false", "~", "", "[1, 2]", "{a: 1}", "!!int 1_0", "!!bool yes", "'x'", "0",
                     "-1", "2147483648", "9" * 40, "&a [*a]", "!!python/object:os.system", "[", "a: b: c"]),
    st.integers(-2**40, 2**40).map(str), st.floats(allow_nan=True).map(repr), st.text(max_size=12))


@PROPERTY
@given(key=st.sampled_from(_KEYS), text=_VALUE_TEXT)
def test_set_values_either_hold_or_name_the_key(key, text):
    section, f = key
    try:
        config = load_config(None, [f"{section}.{f.name}={text}"])
    except ConfigError as e:
        assert "\n" not in str(e) and f"{section}.{f.name}" in str(e), str(e)
        return
    value = getattr(config[section], f.name)
    assert type(value) is type(f.default)
    meta = f.metadata
    if isinstance(value, float):
        assert math.isfinite(value)
    if meta["choices"] is not None:
        assert value in meta["choices"]
    elif isinstance(value, (int, float)) and not isinstance(value, bool) and not (meta["zero_means"] and value == 0):
        assert meta["ge"] is None or value >= meta["ge"]
        assert meta["le"] is None or value <= meta["le"]
        assert meta["gt"] is None or value > meta["gt"]
        assert meta["lt"] is None or value < meta["lt"]


def test_errors_that_guide_to_the_dataset_layout(tmp_path, capsys):
    """A folder of loose panoramas, `images/` itself and an image path each get one line saying what to do."""
    import cv2
    import numpy as np
    from fullview.cli import main
    loose = tmp_path / "loose"
    loose.mkdir()
    for k in range(2):
        cv2.imwrite(str(loose / f"p{k}.png"), np.zeros((8, 16, 3), np.uint8))
    cases = {loose: "move them into", tmp_path / "ds" / "images": "did you mean the dataset folder",
             tmp_path / "ds" / "images" / "p0.png": "is an image, not a dataset"}
    (tmp_path / "ds").mkdir()
    loose.rename(tmp_path / "ds" / "images")
    loose.mkdir()
    for k in range(2):
        cv2.imwrite(str(loose / f"p{k}.png"), np.zeros((8, 16, 3), np.uint8))
    for path, advice in cases.items():
        assert main(["status", str(path), "-w", str(tmp_path / "ws")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and advice in err[0] and err[0].startswith("fullview: error:"), err
