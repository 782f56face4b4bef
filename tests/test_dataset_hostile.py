"""Hostile dataset input: every bad file is a one-line DatasetError naming it, never a traceback or a silent NaN.

Numbered as in the issue "Nothing a user does corrupts a workspace": 1 truncated images, 2 EXIF orientation,
3 odd entries in images/, 4 duplicate YAML keys, 5 hand points, 6 ground truth, 7 OS errors; then property tests.
"""

from __future__ import annotations

import io
import logging
import math
import os
from pathlib import Path

import cv2
import numpy as np
import PIL.Image
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from fullview.io.dataset import Dataset, DatasetError, _jpeg_end
from fullview.io.yamlio import YamlError, dump_yaml, load_yaml

NAMES = ["a.jpg", "b.jpg"]
W, H = 64, 32
IDENTITY = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
# No example database: it would be written into the shared working tree.
PROPERTY = settings(max_examples=150, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])


def _noise(w: int = W, h: int = H, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)  # JPEG needs content


def _make_dataset(root: Path, names=NAMES) -> Path:
    (root / "images").mkdir(parents=True)
    (root / "ground_truth" / "depth").mkdir(parents=True)
    for k, name in enumerate(names):
        assert cv2.imwrite(str(root / "images" / name), _noise(seed=k))
    return root


def _error(fn, path_part: str) -> str:
    """The DatasetError message of fn(): one line, naming the file."""
    with pytest.raises(DatasetError) as info:
        fn()
    message = str(info.value)
    assert "\n" not in message and path_part in message, message
    return message


@pytest.fixture
def ds_root(tmp_path) -> Path:
    return _make_dataset(tmp_path / "ds", [*NAMES, "c.jpg"])


# ------------------------------------------------------------------------------------ 1 truncated images
def _progressive_jpeg(path: Path) -> None:
    params = [cv2.IMWRITE_JPEG_PROGRESSIVE, 1, cv2.IMWRITE_JPEG_RST_INTERVAL, 2]
    assert cv2.imwrite(str(path), _noise(), params)


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
@pytest.mark.parametrize("name", ["a.jpg", "a.png", "progressive"])
def test_truncated_image_is_rejected(tmp_path, fraction, name):
    root = _make_dataset(tmp_path / "ds", ["a.png" if name == "a.png" else "a.jpg", "b.jpg"])
    path = root / "images" / ("a.png" if name == "a.png" else "a.jpg")
    if name == "progressive":
        _progressive_jpeg(path)
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * fraction)])
    message = _error(lambda: Dataset(root).load_image(path.name), path.name)
    assert "cannot read image" in message


def test_every_truncation_of_a_jpeg_is_rejected(tmp_path):
    # Baseline, progressive and restart-marker JPEGs, with an EXIF thumbnail (whose own EOI lies inside the file).
    for k, params in enumerate([[], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1], [cv2.IMWRITE_JPEG_RST_INTERVAL, 1]]):
        ok, encoded = cv2.imencode(".jpg", _noise(seed=k), params)
        data = _with_exif_thumbnail(encoded.tobytes())
        assert _jpeg_end(data) == len(data)
        assert all(_jpeg_end(data[:n]) is None for n in range(len(data) - 1))


def _with_exif_thumbnail(jpeg: bytes) -> bytes:
    thumb = io.BytesIO()
    PIL.Image.fromarray(_noise(16, 8)).save(thumb, "JPEG")
    exif = PIL.Image.Exif()
    exif[0x0112] = 1
    out = io.BytesIO()
    PIL.Image.open(io.BytesIO(jpeg)).save(out, "JPEG", exif=exif.tobytes() + thumb.getvalue())
    return out.getvalue()


def test_complete_png_is_accepted(tmp_path):
    root = _make_dataset(tmp_path / "ds", ["a.png", "b.jpg"])
    assert Dataset(root).load_image("a.png").shape == (H, W, 3)


def test_padding_and_trailer_after_the_image_are_accepted(ds_root):
    path = ds_root / "images" / "a.jpg"
    path.write_bytes(path.read_bytes() + b"\0" * 100 + b"VENDOR TRAILER")
    assert Dataset(ds_root).load_image("a.jpg").shape == (H, W, 3)


@pytest.mark.parametrize("content", [b"", b"\xff\xd8\xff", b"not an image at all"])
def test_garbage_image_is_rejected(ds_root, content):
    (ds_root / "images" / "a.jpg").write_bytes(content)
    _error(lambda: Dataset(ds_root).image_sizes, "a.jpg")


def test_other_format_named_like_an_image_is_rejected(ds_root):
    path = ds_root / "images" / "a.jpg"
    PIL.Image.fromarray(_noise()).save(path, "BMP")
    assert "expected JPEG or PNG" in _error(lambda: Dataset(ds_root).image_sizes, "a.jpg")


# ------------------------------------------------------------------------------------- 2 EXIF orientation
def test_exif_orientation_is_ignored_consistently(ds_root, caplog):
    path = ds_root / "images" / "a.jpg"
    exif = PIL.Image.Exif()
    exif[0x0112] = 6  # "rotate 90° clockwise to display": would make the stored 64x32 a 32x64 image
    PIL.Image.fromarray(_noise()[:, :, ::-1]).save(path, "JPEG", exif=exif.tobytes(), quality=95)
    stored = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    ds = Dataset(ds_root)
    with caplog.at_level(logging.WARNING, logger="fullview.io.dataset"):
        assert ds.image_sizes["a.jpg"] == (W, H)
    assert "EXIF orientation 6 ignored" in caplog.text
    assert np.array_equal(ds.load_image("a.jpg"), stored)
    assert ds.load_image("a.jpg", width=W // 2).shape == (H // 2, W // 2, 3)  # the reduced decode too


# ------------------------------------------------------------------------------ 3 odd entries in images/
def test_folder_named_like_an_image_is_an_error(ds_root):
    (ds_root / "images" / "x.jpg").mkdir()
    assert "not a regular file" in _error(lambda: Dataset(ds_root), "x.jpg")


def test_broken_symlink_is_an_error(ds_root):
    (ds_root / "images" / "d.jpg").symlink_to(ds_root / "gone.jpg")
    assert "broken symbolic link" in _error(lambda: Dataset(ds_root), "d.jpg")


def test_fifo_named_like_an_image_is_an_error_not_a_hang(ds_root):
    os.mkfifo(ds_root / "images" / "d.jpg")
    _error(lambda: Dataset(ds_root), "d.jpg")


def test_symlink_to_an_image_is_fine(ds_root, tmp_path):
    (ds_root / "images" / "b.jpg").rename(tmp_path / "elsewhere.jpg")
    (ds_root / "images" / "b.jpg").symlink_to(tmp_path / "elsewhere.jpg")
    assert Dataset(ds_root).image_sizes["b.jpg"] == (W, H)


def _deny(monkeypatch, path: Path) -> None:
    """chmod 000 the file; as root (who reads it anyway) also make reading it raise what the OS would."""
    path.chmod(0)
    if os.geteuid() == 0:
        real = Path.read_bytes

        def read_bytes(self):
            if self == path:
                raise PermissionError(13, "Permission denied", str(path))
            return real(self)
        monkeypatch.setattr(Path, "read_bytes", read_bytes)


def test_unreadable_image_is_an_error(ds_root, monkeypatch):
    path = ds_root / "images" / "a.jpg"
    _deny(monkeypatch, path)
    ds = Dataset(ds_root)
    assert "Permission denied" in _error(lambda: ds.image_sizes, "a.jpg")
    assert "Permission denied" in _error(lambda: ds.image_hash("a.jpg"), "a.jpg")


# -------------------------------------------------------------------------------------- 4 duplicate keys
def test_duplicate_key_in_hand_points_is_an_error(ds_root):
    (ds_root / "hand_points.yaml").write_text(
        "points:\n  - observations:\n      a.jpg: [1, 2]\n      b.jpg: [3, 4]\n      a.jpg: [5, 6]\n")
    message = _error(lambda: Dataset(ds_root).hand_tracks(), "hand_points.yaml")
    assert "duplicate key 'a.jpg'" in message and "line 5" in message


def test_duplicate_key_in_poses_is_an_error(ds_root):
    (ds_root / "ground_truth" / "poses.yaml").write_text(
        f"cameras:\n  - {{image: a.jpg, R_world_from_cam: {IDENTITY}, center: [0, 0, 0], center: [1, 0, 0]}}\n")
    assert "duplicate key 'center'" in _error(lambda: Dataset(ds_root).ground_truth_poses(), "poses.yaml")


def test_load_yaml_messages_are_one_line_and_name_where(tmp_path):
    for text in ["a: 1\na: 2\n", "a: [\n", "a: !!bool maybe\n", "a: !!timestamp 2024-13-45\n", "[" * 3000, "? [1]\n: 2\n",
                 "\x00", "a: 1\n---\nb: 2\n"]:
        with pytest.raises(YamlError) as info:
            load_yaml(text, "where.yaml")
        assert str(info.value).startswith("where.yaml: not valid YAML") and "\n" not in str(info.value)
    with pytest.raises(YamlError, match="where.yaml: cannot read"):
        load_yaml(tmp_path, "where.yaml")  # a directory
    (tmp_path / "bin.yaml").write_bytes(b"a: \xff\xfe\n")
    with pytest.raises(YamlError, match="not UTF-8"):
        load_yaml(tmp_path / "bin.yaml", "where.yaml")


def test_merge_key_override_is_not_a_duplicate():
    assert load_yaml("base: &b {x: 1, y: 2}\nc:\n  <<: *b\n  x: 3\n", "w") == {"base": {"x": 1, "y": 2},
                                                                               "c": {"x": 3, "y": 2}}


# ------------------------------------------------------------------------------------------ 5 hand points
def _entry(observations: str, extra: str = "") -> str:
    return f"  - {{{extra}observations: {{{observations}}}}}\n"


def _points(observations: str, extra: str = "") -> str:
    return "points:\n" + _entry(observations, extra)


GOOD_OBS = "a.jpg: [1, 2], b.jpg: [3.5, 4]"


@pytest.mark.parametrize("text,problem", [
    ("points: 3\n", "top-level 'points:' list"),
    ("", "top-level 'points:' list"),
    ("points: [5]\n", "needs an 'observations' mapping"),
    (_points("a.jpg: [.nan, 2], b.jpg: [3, 4]"), "finite numbers"),
    (_points("a.jpg: [1, .inf], b.jpg: [3, 4]"), "finite numbers"),
    (_points("a.jpg: [true, 2], b.jpg: [3, 4]"), "expected [x, y]"),
    (_points("a.jpg: ['1', 2], b.jpg: [3, 4]"), "expected [x, y]"),
    (_points("a.jpg: [1, 2, 3], b.jpg: [3, 4]"), "expected [x, y]"),
    (_points("a.jpg: [1, " + "9" * 400 + "], b.jpg: [3, 4]"), "finite numbers"),
    (_points("a.jpg: [-1, 2], b.jpg: [3, 4]"), "lies outside a.jpg (64x32)"),
    (_points("a.jpg: [1, 2]"), "a track needs at least 2"),
    (_points("a.jpg: [1, 2], 7: [3, 4]"), "unknown image 7"),
    (_points(GOOD_OBS, "name: 5, "), "name must be a non-empty string"),
    (_points(GOOD_OBS, "name: '', "), "name must be a non-empty string"),
    (_points(GOOD_OBS, "nmae: x, "), "unknown key(s) ['nmae']"),
    (_points(GOOD_OBS, "name: p, ") + _entry(GOOD_OBS, "name: p, "), "'p' is used twice"),
])
def test_bad_hand_points(ds_root, text, problem):
    (ds_root / "hand_points.yaml").write_text(text)
    assert problem in _error(lambda: Dataset(ds_root).hand_tracks(), "hand_points.yaml")


def test_good_hand_points(ds_root):
    (ds_root / "hand_points.yaml").write_text(_points(GOOD_OBS, "name: corner, ") + _entry(GOOD_OBS))
    tracks = Dataset(ds_root).hand_tracks()
    assert [t.name for t in tracks] == ["corner", "point_1"]
    assert tracks[0].observations == {"a.jpg": (1.0, 2.0), "b.jpg": (3.5, 4.0)}


# ----------------------------------------------------------------------------------------- 6 ground truth
def _camera(image="a.jpg", R=None, center=(0, 0, 0)) -> dict:
    return {"image": image, "R_world_from_cam": IDENTITY if R is None else R, "center": list(center)}


def _write_poses(root: Path, cameras) -> None:
    (root / "ground_truth" / "poses.yaml").write_text(dump_yaml({"cameras": cameras}))


@pytest.mark.parametrize("cameras,problem", [
    ([_camera(R=[[math.nan, 0, 0], [0, 1, 0], [0, 0, 1]])], "R_world_from_cam of 'a.jpg' has a non-finite"),
    ([_camera(center=(0, math.inf, 0))], "center of 'a.jpg' has a non-finite"),
    ([_camera(center=(0, None, 0))], "center of 'a.jpg' must be a 3"),
    ([_camera(center=(0, "1", 0))], "center of 'a.jpg' must be a 3"),
    ([_camera(R=[[True, 0, 0], [0, 1, 0], [0, 0, 1]])], "R_world_from_cam of 'a.jpg' must be a 3x3"),
    ([_camera(R=[[-1, 0, 0], [0, 1, 0], [0, 0, 1]])], "not a rotation matrix"),
    ([_camera(R=[[1e300, 0, 0], [0, 1, 0], [0, 0, 1]])], "not a rotation matrix"),
    ([_camera(), _camera("b.jpg")], "'a.jpg' and 'b.jpg' have coincident centres"),
    ([_camera(center=(1e6, 0, 0)), _camera("b.jpg", center=(1e6, 1e-6, 0)), _camera("c.jpg", center=(-1e6, 0, 0))],
     "'a.jpg' and 'b.jpg' have coincident centres"),
    ([_camera(), _camera()], "'a.jpg' appears twice"),
    ([_camera(image=3)], "unknown image 3"),
    (["a.jpg"], "cameras[0] is invalid"),
])
def test_bad_ground_truth_poses(ds_root, cameras, problem):
    _write_poses(ds_root, cameras)
    assert problem in _error(lambda: Dataset(ds_root).ground_truth_poses(), "poses.yaml")


def test_good_ground_truth_poses(ds_root):
    flat = [0, -1, 0, 1, 0, 0, 0, 0, 1]  # a flat list of 9 is still accepted
    _write_poses(ds_root, [_camera(R=flat, center=(0, 0, 0)), _camera("b.jpg", center=(1e-3, 0, 0))])
    poses = Dataset(ds_root).ground_truth_poses()
    assert poses["a.jpg"].R_world_from_cam.shape == (3, 3) and poses["b.jpg"].center[0] == 1e-3


def _save_depth(root: Path, array, **kwargs) -> Path:
    path = root / "ground_truth" / "depth" / "a.npy"
    np.save(path, array, **kwargs)
    return path


@pytest.mark.parametrize("array,problem", [
    (np.full((4, 8), np.inf, np.float32), "infinite or negative"),
    (np.full((4, 8), -1.0), "infinite or negative"),
    (np.ones((4, 8), np.int32), "2-D float array"),
    (np.ones((4, 8, 1)), "2-D float array"),
    (np.ones((4, 4)), "twice as wide"),
    (np.ones((0, 0)), "2-D float array"),
    (np.array([1.0, None], object), "cannot read depth map"),
])
def test_bad_ground_truth_depth(ds_root, array, problem):
    _save_depth(ds_root, array, allow_pickle=True)
    assert problem in _error(lambda: Dataset(ds_root).ground_truth_depth("a.jpg"), "a.npy")


def test_corrupt_depth_files(ds_root):
    path = _save_depth(ds_root, np.ones((4, 8), np.float32))
    path.write_bytes(path.read_bytes()[:-5])
    _error(lambda: Dataset(ds_root).ground_truth_depth("a.jpg"), "a.npy")
    header = np.lib.format.header_data_from_array_1_0(np.ones((4, 8), np.float32)) | {"shape": (10**6, 2 * 10**6)}
    with open(path, "wb") as f:  # a header claiming 8 TB must not be allocated
        np.lib.format.write_array_header_1_0(f, header)
    _error(lambda: Dataset(ds_root).ground_truth_depth("a.jpg"), "a.npy")
    np.savez(path.with_suffix(".npz"), a=np.ones((4, 8)))
    path.with_suffix(".npz").rename(path)
    assert "not a .npy array" in _error(lambda: Dataset(ds_root).ground_truth_depth("a.jpg"), "a.npy")


def test_depth_with_nan_holes_is_fine(ds_root):
    depth = np.ones((4, 8), np.float32)
    depth[0, 0] = np.nan
    _save_depth(ds_root, depth)
    assert np.array_equal(Dataset(ds_root).ground_truth_depth("a.jpg"), depth, equal_nan=True)


# ---------------------------------------------------------------------------------------------- 7 OS errors
@pytest.mark.parametrize("make", [Path.mkdir, os.mkfifo])  # a FIFO would block the read forever
def test_folders_and_fifos_where_files_belong(ds_root, make):
    make(ds_root / "hand_points.yaml")
    make(ds_root / "ground_truth" / "poses.yaml")
    make(ds_root / "ground_truth" / "depth" / "a.npy")
    ds = Dataset(ds_root)
    _error(ds.hand_tracks, "hand_points.yaml")
    _error(ds.hand_points_hash, "hand_points.yaml")
    _error(ds.ground_truth_poses, "poses.yaml")
    _error(lambda: ds.ground_truth_depth("a.jpg"), "a.npy")


def test_unreadable_yaml(ds_root, monkeypatch):
    path = ds_root / "hand_points.yaml"
    path.write_text(_points(GOOD_OBS))
    path.chmod(0)
    if os.geteuid() == 0:  # root reads it anyway: make reading raise what the OS would
        for reader in ("read_text", "read_bytes"):
            monkeypatch.setattr(Path, reader, lambda self, **kw: (_ for _ in ()).throw(
                PermissionError(13, "Permission denied", str(self))))
    assert "Permission denied" in _error(Dataset(ds_root).hand_tracks, "hand_points.yaml")


# ------------------------------------------------------------------------------------------------ properties
@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Dataset:
    """One 2-image dataset shared by the property tests (each example rewrites its YAML file)."""
    ds = Dataset(_make_dataset(tmp_path_factory.mktemp("hostile") / "ds"))
    assert ds.image_sizes == {n: (W, H) for n in NAMES}
    return ds


_SCALARS = (st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=6)
            | st.sampled_from(NAMES + ["ghost.jpg", "points", "observations", "name", "cameras", "center"]))
_ANYTHING = st.recursive(_SCALARS, lambda inner: st.lists(inner, max_size=4)
                         | st.dictionaries(_SCALARS.filter(lambda k: not isinstance(k, float) or k == k), inner,
                                           max_size=4), max_leaves=16)


def _mostly(valid, invalid):
    """`valid` three times as often as `invalid`, so that examples also reach the end of the validation."""
    return st.sampled_from([valid] * 3 + [invalid]).flatmap(lambda strategy: strategy)


_COORD = _mostly(st.integers(0, H) | st.floats(0, H), st.integers(-2, W + 2) | st.floats() | _SCALARS)
_XY = _mostly(st.lists(_COORD, min_size=2, max_size=2), st.lists(_COORD, max_size=3) | _ANYTHING)
_IMAGE = _mostly(st.sampled_from(NAMES), st.just("ghost.jpg") | _SCALARS)
_OBSERVATIONS = _mostly(st.fixed_dictionaries({n: _XY for n in NAMES}), st.dictionaries(_IMAGE, _XY, max_size=3))
_POINT = _mostly(st.fixed_dictionaries({"observations": _OBSERVATIONS},
                                       optional={"name": _mostly(st.sampled_from(["p", "q", "point_1"]), _SCALARS)}),
                 _ANYTHING)
_HAND_DOC = _mostly(st.fixed_dictionaries({"points": st.lists(_POINT, max_size=3)}), _ANYTHING)

# Fragments of YAML syntax, so that raw text reaches tags, anchors, flow collections and odd scalars.
_YAMLISH = st.lists(st.sampled_from([
    "points:", "cameras:", "\n", "  ", "- ", "observations: ", "name: ", "image: ", "center: ", "R_world_from_cam: ",
    "a.jpg", "b.jpg", ": ", "{", "}", "[", "]", ", ", "1", "2.5", "-3", ".nan", ".inf", "1e400", "9" * 30, "true",
    "~", "'", '"', "#", "\t", "!!bool ", "!!int ", "!!float ", "!!timestamp ", "!!binary ", "!!set ", "&x ", "*x",
    "<<: ", "? ", "---", "|", ">", "%YAML 1.1", "\\", "\x00", "é"]), max_size=40).map("".join)


def _write(path: Path, content) -> None:
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif isinstance(content, str):
        path.write_text(content, encoding="utf-8")
    else:
        path.write_text(dump_yaml(content, sort_keys=False), encoding="utf-8")


def _result_or_error(fn, file_name: str):
    """fn()'s result, or None after checking its DatasetError is one line naming the file; any other exception
    fails the test."""
    try:
        return fn()
    except DatasetError as e:
        assert "\n" not in str(e) and file_name in str(e), str(e)
        return None


def _check_tracks(ds: Dataset) -> None:
    """hand_tracks() is valid or a one-line DatasetError naming the file; nothing else."""
    tracks = _result_or_error(ds.hand_tracks, "hand_points.yaml")
    if tracks is None:
        return
    assert len({t.name for t in tracks}) == len(tracks)
    for t in tracks:
        assert isinstance(t.name, str) and t.name and len(t.observations) >= 2
        for image, (x, y) in t.observations.items():
            assert image in NAMES and math.isfinite(x) and math.isfinite(y) and 0 <= x <= W and 0 <= y <= H


@PROPERTY
@given(doc=_HAND_DOC)
def test_hand_points_structures(tiny, doc):
    _write(tiny.hand_points_path, doc)
    _check_tracks(tiny)


_RAW = _YAMLISH | st.text(max_size=60) | st.binary(max_size=60)


@PROPERTY
@given(text=_RAW)
def test_hand_points_raw_text(tiny, text):
    _write(tiny.hand_points_path, text)
    _check_tracks(tiny)


def _rotation(q) -> list[list[float]]:
    w, x, y, z = (float(v) for v in np.asarray(q) / np.linalg.norm(q))
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]


_QUATERNION = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1)
_MATRIX = _mostly(_QUATERNION.map(_rotation),
                  st.lists(st.lists(_COORD, min_size=3, max_size=3), min_size=3, max_size=3) | _ANYTHING)
_CENTER = _mostly(st.lists(st.floats(-10, 10) | st.sampled_from([0, 1e-12]), min_size=3, max_size=3),
                  st.lists(_COORD, min_size=3, max_size=3) | _ANYTHING)
_CAMERA = _mostly(st.fixed_dictionaries({"image": _IMAGE, "R_world_from_cam": _MATRIX, "center": _CENTER}), _ANYTHING)
_POSES_DOC = _mostly(st.fixed_dictionaries({"cameras": st.lists(_CAMERA, max_size=3)}), _ANYTHING)


def _check_poses(ds: Dataset) -> None:
    """ground_truth_poses() is valid or a one-line DatasetError naming the file; nothing else."""
    poses = _result_or_error(ds.ground_truth_poses, "poses.yaml")
    if poses is None:
        return
    for image, pose in poses.items():
        R, c = pose.R_world_from_cam, pose.center
        assert image in NAMES and R.shape == (3, 3) and c.shape == (3,)
        assert np.isfinite(R).all() and np.isfinite(c).all()
        assert np.abs(R.T @ R - np.eye(3)).max() <= 1e-6 and np.linalg.det(R) > 0
    centers = [tuple(p.center) for p in poses.values()]
    assert len(set(centers)) == len(centers)


@PROPERTY
@given(doc=_POSES_DOC)
def test_ground_truth_structures(tiny, doc):
    _write(tiny.ground_truth_dir / "poses.yaml", doc)
    _check_poses(tiny)


@PROPERTY
@given(text=_RAW)
def test_ground_truth_raw_text(tiny, text):
    _write(tiny.ground_truth_dir / "poses.yaml", text)
    _check_poses(tiny)


_KEYS = st.text(min_size=1, max_size=8)
_PLAIN = st.integers() | st.text(max_size=8) | st.booleans() | st.none()


@PROPERTY
@given(mapping=st.dictionaries(_KEYS, _PLAIN, min_size=1, max_size=5), data=st.data(), nested=st.booleans())
def test_yaml_with_a_duplicate_key_always_raises(mapping, data, nested):
    key = data.draw(st.sampled_from(sorted(mapping)))
    text = dump_yaml(mapping) + dump_yaml({key: data.draw(_PLAIN)})
    if nested:
        text = "outer:\n" + "".join(f"  {line}\n" for line in text.splitlines())
    assert load_yaml(dump_yaml(mapping), "w") == mapping  # no false alarm without the repeat
    with pytest.raises(YamlError, match=r"^w: not valid YAML .*duplicate key"):
        load_yaml(text, "w")
