"""The speed-ups of issue 12's third pass compute exactly what the serial / straightforward code computed."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.io.dataset import Dataset
from fullview.sfm import manhattan, two_view, upright
from fullview.sfm.camera import normalize
from fullview.stages import filter as filter_stage
from tests.test_upright import _render_room


def test_gravity_in_threads_equals_serial(tiny_dataset):
    ds = Dataset(tiny_dataset)
    ctx = SimpleNamespace(dataset=ds, options=SimpleNamespace(seed=3))
    gravity, std, (axis, axis_std, refined, refined_std) = filter_stage._gravity(ctx, "vanishing")
    serial = []
    for name in ds.image_names:
        image = ds.load_image(name, width=min(filter_stage.GRAVITY_WIDTH, ds.image_sizes[name][0]))
        serial.append((image, upright.estimate_gravity_with_std(image, min_lines=filter_stage.GRAVITY_MIN_LINES,
                                                                seed=3)))
    assert any(found is not None for _, found in serial)  # the comparison must cover found gravities
    for k, (image, found) in enumerate(serial):
        if found is None:
            assert np.isnan(gravity[k]).all() and np.isnan(std[k]) and np.isnan(axis_std[k])
            continue
        assert np.array_equal(gravity[k], found[0]) and std[k] == found[2]
        # the Manhattan frame, from the image's lines about that gravity, as triangulation's heading prior reads it
        normals, lengths = upright.detect_line_normals(image)
        found_axis = manhattan.manhattan_axis(normals, lengths, found[0])
        if found_axis is None:
            assert np.isnan(axis_std[k]) and np.isnan(refined[k]).all()
            continue
        g, a, g_std, a_std = manhattan.manhattan_frame(normals, lengths, found[0], found_axis[0])
        assert np.array_equal(refined[k], g) and np.array_equal(axis[k], a)
        assert refined_std[k] == g_std and axis_std[k] == a_std


def test_the_filter_stores_the_manhattan_frame_of_the_lines_that_gave_its_gravity():
    R = Rotation.from_euler("xyz", [2.0, 30.0, -1.0], degrees=True).as_matrix()
    image = _render_room(R)
    dataset = SimpleNamespace(image_sizes={"room.png": (image.shape[1], image.shape[0])},
                              load_image=lambda name, width: image)
    found, frame = filter_stage._image_gravity(dataset, 3, "room.png")
    normals, lengths = upright.detect_line_normals(image)
    axis = manhattan.manhattan_axis(normals, lengths, found[0])
    assert axis is not None and frame is not None  # the box room's edges give one pair of wall directions
    for stored, direct in zip(frame, manhattan.manhattan_frame(normals, lengths, found[0], axis[0])):
        assert np.array_equal(stored, direct)
    # the room's walls run along its world x and z axes: the axis, carried to the world, lies along one of them
    world_axis = R.T @ frame[1]
    assert min(abs(world_axis[0]), abs(world_axis[2])) < np.sin(np.radians(0.5))


def test_epipoles_in_threads_equal_each_pair_alone(tiny_dataset, make_pipeline):
    pipe = make_pipeline(tiny_dataset)
    pipe.run(until="epipoles")
    stored, verified = pipe.ws.load_epipoles(), pipe.ws.load_inliers()
    obs = pipe.ws.load_observations(pipe.dataset)
    assert stored["valid"].sum() >= 2
    for k, (i, j) in enumerate(verified.pairs):
        m = verified.matches[k]
        pose = two_view.relative_pose_from_f(verified.extra["F"][k], obs[i]["bearings"][m[:, 0]],
                                             obs[j]["bearings"][m[:, 1]])
        assert np.array_equal(stored["R_j_from_i"][k], pose.R_j_from_i)
        assert np.array_equal(stored["t_j_from_i"][k], pose.t_j_from_i)
        assert stored["num_cheiral"][k] == pose.num_cheiral


def test_local_optimization_scores_each_model_once_and_finds_the_same_fit():
    """The re-fit loop reuses each model's errors for its score and its next inliers: the model and cost equal
    those of scoring every model afresh."""
    rng = np.random.default_rng(0)
    R = Rotation.from_rotvec([0.05, 0.4, -0.02]).as_matrix()
    X = rng.uniform(-4, 4, (400, 3)) + [0, 0, 6] * rng.choice([-1, 1], (400, 1))
    b_i = normalize(X)
    b_j = normalize((X - [1.0, 0.1, 0.3]) @ R.T)
    b_j[:80] = normalize(rng.normal(size=(80, 3)))  # outliers
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(0.05), (400, 3))).as_matrix()
    b_j = np.einsum("nab,nb->na", noise, b_j)
    F0 = two_view.estimate_f_linear(b_i[80:90], b_j[80:90])
    threshold = np.radians(0.35)
    F, cost = two_view._local_optimization(b_i, b_j, F0, threshold, steps=4)
    # reference: the loop as written before, every model's errors computed again
    best_F, best_cost = F0, two_view._msac_scores(two_view.epipolar_angular_errors(F0, b_i, b_j), threshold).sum()
    current = F0
    for factor in two_view.LO_THRESHOLD_SCHEDULE[:4]:
        errors = two_view.epipolar_angular_errors(current, b_i, b_j)
        inliers = errors < factor * threshold
        w = 1.0 / (1.0 + (errors[inliers] / (factor * threshold)) ** 2)
        current = two_view.estimate_f_linear(b_i[inliers], b_j[inliers], w)
        c = two_view._msac_scores(two_view.epipolar_angular_errors(current, b_i, b_j), threshold).sum()
        if c < best_cost:
            best_F, best_cost = current, c
    assert np.array_equal(F, best_F) and cost == best_cost
    assert cost < two_view._msac_scores(two_view.epipolar_angular_errors(F0, b_i, b_j), threshold).sum()


def test_bundle_adjustment_residuals_in_two_halves_equal_one_piece(monkeypatch):
    """`bundle._residuals` splits large problems over two threads: the residuals, the Jacobian blocks and the whole
    adjustment's result are bitwise those of the one-piece computation."""
    from fullview.sfm import bundle

    rng = np.random.default_rng(0)
    n, num_points = 5, 400
    centers = rng.normal(0, 1, (n, 3))
    R = Rotation.from_rotvec(rng.normal(0, 0.2, (n, 3))).as_matrix()
    t = -np.einsum("nij,nj->ni", R, centers)
    X = rng.normal(0, 3, (num_points, 3))
    cam = np.concatenate([rng.choice(n, 3, replace=False) for _ in range(num_points)])
    pt = np.repeat(np.arange(num_points), 3)
    bearings = normalize(np.einsum("kij,kj->ki", R[cam], X[pt] - centers[cam]) + rng.normal(0, 1e-3, (len(cam), 3)))
    args = dict(R_cam_from_world=R, t_cam_from_world=t, points=X + rng.normal(0, 0.02, X.shape), obs_camera=cam,
                obs_point=pt, obs_bearings=bearings, fixed_cameras=(0,), loss="soft_l1", max_nfev=20)
    seen = []
    one_piece = bundle._residuals
    monkeypatch.setattr(bundle, "_residuals", lambda x, p, j: seen.append((x.copy(), p)) or one_piece(x, p, j))
    serial = bundle.bundle_adjust(**args)
    monkeypatch.setattr(bundle, "_residuals", one_piece)
    monkeypatch.setattr(bundle, "PARALLEL_MIN_OBSERVATIONS", 100)  # 1,200 observations: two halves
    x, problem = seen[-1]
    monkeypatch.setattr(bundle, "PARALLEL_MIN_OBSERVATIONS", 10**9)
    r_one, J_one = bundle._residuals(x, problem, True)
    monkeypatch.setattr(bundle, "PARALLEL_MIN_OBSERVATIONS", 100)
    r_two, J_two = bundle._residuals(x, problem, True)
    assert np.array_equal(r_one, r_two) and np.array_equal(J_one, J_two)
    halves = bundle.bundle_adjust(**args)
    assert serial.final_cost < serial.initial_cost
    for key in ("R_cam_from_world", "t_cam_from_world", "points", "obs_error_rad"):
        assert np.array_equal(getattr(serial, key), getattr(halves, key))


def test_matches_stage_stores_each_pairs_own_matches_when_blocks_run_largest_first(tmp_path, make_pipeline):
    """The matches stage hands out its blocks of pairs largest first (5 images: blocks of 4, 2, 2, 1, 1 pairs, not
    in index order); every stored pair must still hold that pair's own matches."""
    from fullview.sfm.matching import descriptor_basis, match_pair, project_descriptors
    from fullview.synth import write_synthetic_dataset

    pipe = make_pipeline(write_synthetic_dataset(tmp_path / "five", views=5, width=512, seed=2))
    pipe.run(until="matches")
    stored = pipe.ws.load_matches()
    options = pipe.config["matches"]
    full = [pipe.ws.load_features(n)["descriptors"] for n in pipe.dataset.image_names]
    noise = [float(pipe.ws.load_features(n, ("noise_sigma",))["noise_sigma"]) for n in pipe.dataset.image_names]
    basis = descriptor_basis(full, options.descriptor_dims)
    assert len(stored.pairs) == 10
    for k, ((i, j), m) in enumerate(zip(stored.pairs, stored.matches)):
        own, strict = match_pair(project_descriptors(full[i], basis), project_descriptors(full[j], basis), options,
                                 noise[i], noise[j], full=(full[i], full[j]))
        assert len(own) > 20 and np.array_equal(m, own) and stored.extra["num_strict"][k] == strict


def test_matches_stage_reads_gps_only_when_the_pair_selection_uses_it(tiny_dataset, make_pipeline, monkeypatch):
    """Exhaustive sets never look at GPS (a PNG's EXIF costs a full decode); `auto` above its exhaustive size does."""
    calls = []
    original = Dataset.gps_positions
    monkeypatch.setattr(Dataset, "gps_positions", lambda self: calls.append(1) or original(self))
    make_pipeline(tiny_dataset).run(until="matches")
    assert calls == []
    pipe = make_pipeline(tiny_dataset, ["matches.auto_exhaustive_below=2"], workspace=None)
    pipe.run(until="matches", force=True)
    assert calls == [1]


def _point_descriptors_with_add_at(tracks, cameras, point_of_track, descriptors):
    """The loop as it was before the buffered add (np.add.at for every image)."""
    num_sift = np.array([len(d) for d in descriptors])
    sel = (cameras[tracks.image_ids] & (point_of_track[tracks.track_ids] >= 0)
           & (tracks.feature_ids < num_sift[tracks.image_ids]))
    rows = point_of_track[tracks.track_ids[sel]]
    sums = np.zeros((len(point_of_track[point_of_track >= 0]), descriptors[0].shape[1]))
    for b in np.unique(tracks.image_ids[sel]):
        here = tracks.image_ids[sel] == b
        np.add.at(sums, rows[here], descriptors[b][tracks.feature_ids[sel][here]])
    return (sums / np.maximum(np.linalg.norm(sums, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def test_point_descriptors_buffered_add_equals_add_at():
    from fullview.sfm.registration.models import _point_descriptors
    from fullview.sfm.tracks import Tracks

    rng = np.random.default_rng(5)
    n_images, n_tracks = 5, 400
    descriptors = [rng.random((300, 128), dtype=np.float32) for _ in range(n_images)]
    image_ids, feature_ids, track_ids = [], [], []
    for t in range(n_tracks):
        seen = np.sort(rng.choice(n_images, size=rng.integers(2, n_images + 1), replace=False))
        if t % 50 == 0:  # a track meeting one image twice: the np.add.at fallback must give the same sums
            seen = np.sort(np.append(seen, seen[0]))
        image_ids += seen.tolist()
        feature_ids += rng.integers(0, 320, len(seen)).tolist()  # some beyond the SIFT rows: skipped
        track_ids += [t] * len(seen)
    track_ids = np.array(track_ids)
    tracks = Tracks(track_ids=track_ids, image_ids=np.array(image_ids), feature_ids=np.array(feature_ids),
                    offsets=np.searchsorted(track_ids, np.arange(n_tracks + 1)), num_images=n_images)
    cameras = np.array([True, True, False, True, True])
    point_of_track = np.where(rng.random(n_tracks) < 0.8, 0, -1)
    point_of_track[point_of_track >= 0] = rng.permutation((point_of_track >= 0).sum())
    got, track_of_point = _point_descriptors(tracks, cameras, point_of_track, descriptors)
    want = _point_descriptors_with_add_at(tracks, cameras, point_of_track, descriptors)
    assert got.tobytes() == want.tobytes()  # bitwise: the sums are added in the same order
    assert np.array_equal(point_of_track[track_of_point], np.arange(len(got)))


def test_basis_from_moments_on_threads_is_descriptor_basis_bitwise():
    from fullview.sfm.matching import basis_from_moments, descriptor_basis, second_moment
    from fullview.stages.protocol import thread_map

    rng = np.random.default_rng(11)
    sets = [normalize(rng.random((int(n), 128))).astype(np.float32) for n in rng.integers(50, 400, 7)]
    for dims in (16, 32):
        got = basis_from_moments(thread_map(second_moment, sets, threads=2), dims)
        assert got.tobytes() == descriptor_basis(sets, dims).tobytes()
    assert basis_from_moments(map(second_moment, sets), 0) is None


def test_partial_feature_loads_equal_the_full_load(tiny_dataset, make_pipeline):
    pipe = make_pipeline(tiny_dataset)
    pipe.run(until="features")
    name = pipe.dataset.image_names[0]
    full = pipe.ws.load_features(name)
    part = pipe.ws.load_features(name, ("pixels", "image_size"))
    assert sorted(part) == ["image_size", "pixels"]
    assert all(np.array_equal(part[k], full[k]) for k in part)
    assert np.array_equal(pipe.ws.load_descriptors(name), full["descriptors"])


def test_rescoring_in_chunks_of_rows_equals_all_rows_at_once():
    """`_rescore` works RESCORE_ROWS rows at a time (the temporary stays in cache): the same neighbours and the
    same distance bits as one pass over every row, also with a last partial chunk."""
    from fullview.sfm.matching import _rescore

    rng = np.random.default_rng(4)
    unit = lambda n: normalize(np.abs(rng.normal(size=(n, 128)))).astype(np.float32)  # noqa: E731
    full_i, full_j = unit(1000), unit(700)
    nn = rng.integers(0, 700, (1000, 4))
    nn[::7, 1] = nn[::7, 0]  # tied candidates: the stable order must be kept
    one = _rescore(nn, full_i, full_j, rows=1000)
    for rows in (1, 256, 333):
        chunked = _rescore(nn, full_i, full_j, rows=rows)
        assert np.array_equal(one[0], chunked[0]) and np.array_equal(one[1], chunked[1])


def _noisy_ring_adjustment(rng, n=6, num_points=500, gravity=False):
    """bundle_adjust arguments of a ring of n cameras seeing noisy bearings of points around them (tracks of 3),
    from perturbed poses and points; with `gravity`, a gravity prior on every camera."""
    from fullview.sfm.bundle import GravityPrior

    centers = rng.normal(0, 1, (n, 3))
    R = Rotation.from_rotvec(rng.normal(0, 0.2, (n, 3))).as_matrix()
    X = rng.normal(0, 3, (num_points, 3))
    cam = np.concatenate([rng.choice(n, 3, replace=False) for _ in range(num_points)])
    pt = np.repeat(np.arange(num_points), 3)
    bearings = normalize(np.einsum("kij,kj->ki", R[cam], X[pt] - centers[cam]) + rng.normal(0, 1e-3, (len(cam), 3)))
    R0 = Rotation.from_rotvec(rng.normal(0, 0.01, (n, 3))).as_matrix() @ R
    R0[0] = R[0]
    C0 = centers + rng.normal(0, 0.02, centers.shape)
    C0[0] = centers[0]
    prior = None
    if gravity:
        down = normalize(np.einsum("nij,j->ni", R, [0.0, -1.0, 0.0]) + rng.normal(0, 1e-3, (n, 3)))
        prior = GravityPrior(camera=np.arange(n), gravity_cam=down, up_world=np.tile([0.0, -1.0, 0.0], (n, 1)),
                             group=np.zeros(n, np.int64), sigma_rad=np.full(n, 1e-3))
    return dict(R_cam_from_world=R0, t_cam_from_world=-np.einsum("nij,nj->ni", R0, C0),
                points=X + rng.normal(0, 0.05, X.shape), obs_camera=cam, obs_point=pt, obs_bearings=bearings,
                fixed_cameras=(0,), loss="soft_l1", loss_scale_rad=2e-3, gravity_prior=prior)


def test_closed_form_3x3_inverse_and_cholesky_equal_lapacks():
    """`bundle._inverse_spd3` and `_cholesky3` (the Schur solve's per-point 3×3 blocks) give numpy's LAPACK results
    to rounding, down to condition numbers far beyond a triangulated point's."""
    from fullview.sfm.bundle import _cholesky3, _inverse_spd3

    rng = np.random.default_rng(3)
    for condition in (1.0, 1e3, 1e6):
        Q = Rotation.random(200, random_state=rng).as_matrix()
        eig = np.exp(rng.uniform(0, np.log(condition), (200, 3)))
        eig[:, 0] = 1.0
        A = np.einsum("nij,nj,nkj->nik", Q, eig, Q) * rng.uniform(1e-4, 1e4, (200, 1, 1))
        A = 0.5 * (A + A.transpose(0, 2, 1))
        inverse = np.linalg.inv(A)
        np.testing.assert_allclose(_inverse_spd3(A), inverse, rtol=0, atol=1e-13 * condition * np.abs(inverse).max())
        np.testing.assert_allclose(_cholesky3(A), np.linalg.cholesky(A), rtol=0,
                                   atol=1e-13 * condition * np.abs(np.linalg.cholesky(A)).max())
    # Where LAPACK raises (not positive definite, singular), the closed forms give NaN / inf, which the solve treats
    # as a failed factorisation.
    assert np.isnan(_cholesky3(np.diag([1.0, 1.0, -1.0])[None])).any()
    assert not np.isfinite(_inverse_spd3(np.zeros((1, 3, 3)))).all()


def test_schur_products_from_a_contiguous_transpose_and_closed_forms_keep_the_adjustment(monkeypatch):
    """The Schur solve takes its per-observation products from a contiguous Jᵀ and inverts / factors the 3×3 point
    blocks in closed form: each step equals the step of numpy's LAPACK inverse and Cholesky to 1e-9, and the whole
    adjustment ends at the same poses, points and cost (with and without a gravity prior)."""
    from fullview.sfm import bundle

    for gravity in (False, True):
        args = _noisy_ring_adjustment(np.random.default_rng(4), gravity=gravity)
        fast = bundle.bundle_adjust(**args)
        steps = []
        solve = bundle._SchurSystem.solve
        monkeypatch.setattr(bundle._SchurSystem, "solve", lambda self, *a: steps.append((self, a)) or solve(self, *a))
        bundle.bundle_adjust(**args)
        monkeypatch.setattr(bundle._SchurSystem, "solve", solve)
        monkeypatch.setattr(bundle, "_inverse_spd3", np.linalg.inv)
        monkeypatch.setattr(bundle, "_cholesky3", np.linalg.cholesky)
        for system, a in steps[:3]:
            step, _ = solve(system, *a)
            monkeypatch.undo()
            step_fast, _ = solve(system, *a)
            monkeypatch.setattr(bundle, "_inverse_spd3", np.linalg.inv)
            monkeypatch.setattr(bundle, "_cholesky3", np.linalg.cholesky)
            np.testing.assert_allclose(step_fast, step, rtol=0, atol=1e-9 * np.abs(step).max())
        lapack = bundle.bundle_adjust(**args)
        monkeypatch.undo()
        assert fast.num_evaluations == lapack.num_evaluations
        assert fast.final_cost == pytest.approx(lapack.final_cost, rel=1e-9)
        np.testing.assert_allclose(fast.R_cam_from_world, lapack.R_cam_from_world, rtol=0, atol=1e-10)
        np.testing.assert_allclose(fast.points, lapack.points, rtol=0, atol=1e-8)


def test_pose_tolerance_stops_once_the_cameras_settle_and_changes_nothing_when_off():
    """`bundle_adjust(pose_tolerance_rad=...)` (the triangulation's pose round): 0 is exactly the default; a
    tolerance stops the reweighting rounds earlier, at poses within a few tolerances of the full run's."""
    from fullview.sfm import bundle

    args = _noisy_ring_adjustment(np.random.default_rng(5), gravity=True)
    full = bundle.bundle_adjust(**args)
    off = bundle.bundle_adjust(**args, pose_tolerance_rad=0.0)
    for key in ("R_cam_from_world", "t_cam_from_world", "points", "obs_error_rad"):
        assert np.array_equal(getattr(full, key), getattr(off, key))
    tolerance = np.radians(0.005)
    early = bundle.bundle_adjust(**args, pose_tolerance_rad=tolerance)
    assert early.num_evaluations < full.num_evaluations
    relative = np.einsum("nij,nkj->nik", early.R_cam_from_world, full.R_cam_from_world)
    angles = np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert angles.max() < 3 * tolerance
    assert early.final_cost == pytest.approx(full.final_cost, rel=1e-3)


def test_stages_run_with_single_threaded_blas_from_the_cached_controller(tiny_dataset, make_pipeline, monkeypatch):
    """The runner limits BLAS to one thread per stage through one cached threadpoolctl controller (rescanned only
    after imports): inside every stage each BLAS library reports one thread, afterwards its own count again; a
    module imported since forces a new scan."""
    import sys

    from threadpoolctl import threadpool_info

    from fullview.stages import features as features_stage
    from fullview.stages import runner

    before = {info["filepath"]: info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas"}
    seen = []
    run = features_stage.run
    monkeypatch.setattr(features_stage, "run", lambda ctx: seen.append(
        [info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas"]) or run(ctx))
    pipe = make_pipeline(tiny_dataset)
    pipe.run(until="features")
    controller = runner._blas_controller()
    assert runner._blas_controller() is controller  # no import since: the same scan
    assert seen and seen[0] and set(seen[0]) == {1}
    after = {info["filepath"]: info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas"}
    assert after == before
    monkeypatch.setitem(sys.modules, "fullview_test_new_module", SimpleNamespace())
    assert runner._blas_controller() is not controller


def test_registration_reads_descriptors_only_when_matching_needs_them(tiny_dataset, make_pipeline, monkeypatch,
                                                                     tmp_path):
    """Registration's descriptors are read lazily (`NormalisedDescriptors`): where the view graph places every image
    none is read, and the stored registration is byte for byte the one with every image's descriptors read first."""
    from fullview.io.workspace import Workspace
    from fullview.stages import registration as registration_stage

    lazy, eager = (make_pipeline(tiny_dataset, workspace=tmp_path / name) for name in ("lazy", "eager"))
    for pipe in (lazy, eager):
        pipe.run(until="epipoles")
    reads = []
    load = Workspace.load_descriptors
    monkeypatch.setattr(Workspace, "load_descriptors", lambda self, name: reads.append(name) or load(self, name))
    lazy.run(until="registration")
    assert lazy.ws.load_registration()["registered"].all() and reads == []
    read_all = registration_stage._descriptors
    monkeypatch.setattr(registration_stage, "_descriptors",
                        lambda ctx, obs: [read_all(ctx, obs)[k] for k in range(len(obs))])
    eager.run(until="registration")
    assert len(reads) == len(lazy.dataset.image_names)  # the list read every image's descriptors
    files = [p for p in (lazy.ws.root / "registration").rglob("*") if p.is_file() and p.name != "manifest.json"]
    assert files
    for path in files:
        assert path.read_bytes() == (eager.ws.root / "registration" / path.relative_to(lazy.ws.root / "registration")
                                     ).read_bytes()


def test_feature_files_are_hashed_by_their_writing_task_and_rehashed_when_changed(tmp_path, monkeypatch):
    """`StageWriter.save_features` takes the file's sha256 on the writing task; the manifest reuses it (no second
    read of the file) while size and mtime match, and hashes the file again once it was rewritten."""
    from fullview.io import workspace as workspace_module
    from fullview.io.workspace import FEATURE_KEYS, StageWriter

    rng = np.random.default_rng(0)
    arrays = {k: rng.normal(size=(5, 3)) for k in FEATURE_KEYS}
    writer = StageWriter("features", tmp_path)
    first = writer.save_features("a.png", **arrays)
    second = writer.save_features("b.png", **arrays)
    hashed = []
    sha256 = workspace_module.file_sha256
    monkeypatch.setattr(workspace_module, "file_sha256", lambda p: hashed.append(p) or sha256(p))
    manifest = writer.commit_manifest({})
    assert hashed == []
    for path in (first, second):
        assert manifest["outputs"][path.name]["sha256"] == sha256(path)
    second.write_bytes(second.read_bytes() + b"changed")
    manifest = writer.commit_manifest({})
    assert hashed == [second] and manifest["outputs"][second.name]["sha256"] == sha256(second)


def _features_described_in_full(image, options):
    """The features as computed before SIFT's descriptors were limited to the kept keypoints: every face described
    in full (its threshold lowered on plain faces), then the keypoints outside the face's own square and the
    latitudes dropped."""
    from fullview.sfm import features as ft
    from fullview.sfm.camera import bearings_to_lonlat

    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    size = options.face_size or ft.native_face_size(grey.shape[1], options.margin_deg)
    faces, focal = ft.render_faces(grey, size, options.margin_deg)
    bearings, descriptors = [], []
    for f, face in enumerate(faces):
        threshold = options.contrast_threshold
        while True:
            sift = cv2.SIFT_create(nfeatures=options.max_features_per_face, contrastThreshold=threshold)
            keypoints, desc = sift.detectAndCompute(face, None)
            if len(keypoints) >= options.min_features_per_face or threshold / 2 < options.min_contrast_threshold:
                break
            threshold /= 2
        if keypoints:
            b = ft.face_keypoints_to_bearings(np.array([k.pt for k in keypoints]) + ft.OPENCV_SIFT_TO_CONTINUOUS, f,
                                              size, focal)
            _, lat = bearings_to_lonlat(b)
            keep = ft.owned_by_face(b, f) & (lat >= np.radians(options.min_latitude_deg)) & \
                (lat <= np.radians(options.max_latitude_deg))
            bearings.append(b[keep])
            descriptors.append(desc[keep])
    return np.concatenate(bearings), np.concatenate(descriptors)


@pytest.mark.parametrize("contrast,wanted", [(6.0, 300), (60.0, 300), (60.0, 380)])
def test_features_described_only_where_kept_equal_described_in_full(contrast, wanted):
    """SIFT describes only the keypoints a face keeps (OpenCV's mask) on faces expected to keep enough, whichever way
    the hint picks for each face: the same bearings and descriptors, bit for bit, on plain
    panoramas (thresholds lowered), textured ones, and faces that keep too few of enough keypoints (380 of 400),
    with the nadir cap cutting through the down face."""
    from fullview.sfm import features as ft
    from fullview.sfm.options import FeaturesOptions

    rng = np.random.default_rng(5)
    noise = cv2.GaussianBlur(rng.standard_normal((256, 512)), (0, 0), 1.5)
    image = (128 + contrast * noise).clip(0, 255).astype(np.uint8)
    options = FeaturesOptions(min_latitude_deg=-65.0, max_features_per_face=400, min_features_per_face=wanted)
    bearings, descriptors = _features_described_in_full(image, options)
    hints = []
    for hint in (None, set(), set(range(6)), {0, 4}):
        feats = ft.detect_features(image, options, hint)
        assert np.array_equal(feats.bearings, bearings)
        assert np.array_equal(feats.descriptors, np.sqrt(descriptors / descriptors.sum(axis=1, keepdims=True)))
        hints.append(hint)
    # the plain panorama and the high minimum keep too few on every face, the textured one on none: both ways taken
    assert hints[1] == (set() if contrast > 10 and wanted == 300 else set(range(6)))
