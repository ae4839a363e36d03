"""The annealed particle filter's parts against independent references: the resampler and the truncated Gaussian by
their distributions over many draws, the annealing exponent against its definition, the polish against a plain
Levenberg-Marquardt loop; the marker set's fit on a body with known markers; and the filter tracking a capture's
markers seen through the simulated detector (the epipolar cost: tests/test_epipolar.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from conftest import DEMO_RIG, demo_rig, shared_data
from torchtrack.cameras import load_calibration
from torchtrack.checks import InputError
from torchtrack.markers.model import MarkerSet, assign_markers, fit_marker_set
from torchtrack.skeleton import Skeleton
from torchtrack.tracking.epipolar import pinhole_pixels, projection_matrices
from torchtrack.tracking.particles import APFConfig, annealing_beta, resample, truncated_normal

def test_resampling_draws_in_proportion_to_the_weights():
    gen = torch.Generator().manual_seed(1)
    w = torch.rand(40, generator=gen, dtype=torch.float64) * 7.0  # unnormalised
    w[5] = 0.0
    N, draws = w.numel(), 2000
    counts = torch.zeros(N, dtype=torch.float64)
    for _ in range(draws):
        idx = resample(w, gen)
        c = torch.bincount(idx, minlength=N).double()
        assert ((c - w / w.sum() * N).abs() < 1).all()  # systematic: within one copy of N w
        counts += c
    expected = (w / w.sum() * N * draws).numpy()
    assert counts[5] == 0
    keep = expected > 0
    # systematic resampling's counts vary less than multinomial ones: the mean of each count must match
    z = (counts.numpy()[keep] - expected[keep]) / np.sqrt(draws * 0.25)  # a count's spread is at most 1/2 a draw
    assert np.abs(z).max() < 5
    # rows are resampled each by its own weights
    rows = resample(torch.stack([w, w.flip(0)]), gen)
    assert (torch.bincount(rows[0], minlength=N)[5] == 0) and (torch.bincount(rows[1], minlength=N)[N - 6] == 0)


@pytest.mark.parametrize("mean, std, lo, hi", [(0.0, 1.0, -0.5, 2.0), (1.0, 0.3, 1.2, 1.5), (0.0, 2.0, -1.0, 1.0)])
def test_truncated_normal_has_its_distribution(mean, std, lo, hi):
    gen = torch.Generator().manual_seed(2)
    x = truncated_normal(torch.full((20000, 1), mean, dtype=torch.float64), torch.tensor([std], dtype=torch.float64),
                         torch.tensor([lo]), torch.tensor([hi]), gen).numpy().ravel()
    assert x.min() >= lo and x.max() <= hi
    ref = stats.truncnorm((lo - mean) / std, (hi - mean) / std, loc=mean, scale=std)
    assert stats.kstest(x, ref.cdf).pvalue > 1e-3


def test_annealing_beta_hits_the_survival_rate():
    gen = torch.Generator().manual_seed(3)
    cost = torch.rand(500, generator=gen, dtype=torch.float64) ** 2 * 1e4
    for target in (0.2, 0.5, 0.8):
        beta = annealing_beta(cost, target)
        w = torch.exp(-beta * (cost - cost.min()))
        assert float(w.sum() ** 2 / (w.numel() * (w * w).sum())) == pytest.approx(target, abs=1e-3)
    # rows of different scales at once, each its own beta; a row of equal costs gets 0
    rows = torch.stack([cost, 1e-3 * cost.flip(0), torch.full_like(cost, 7.0)])
    betas = annealing_beta(rows, 0.5)
    for r in range(2):
        w = torch.exp(-betas[r] * (rows[r] - rows[r].min()))
        assert float(w.sum() ** 2 / (w.numel() * (w * w).sum())) == pytest.approx(0.5, abs=1e-3)
    assert float(betas[2]) == 0.0
    # costs of any scale, a tie at the least among them, an infinite one
    for scale in (1e-12, 1e12):
        row = torch.cat([cost[cost.argmin()][None], cost]) * scale
        beta = annealing_beta(torch.cat([row, torch.tensor([math.inf], dtype=row.dtype)]), 0.5)
        w = torch.exp(-beta * (row - row.min()))
        assert float(w.sum() ** 2 / ((w.numel() + 1) * (w * w).sum())) == pytest.approx(0.5, abs=1e-3)
        w = torch.exp(-annealing_beta(row, 0.5) * (row - row.min()))
        assert float(w.sum() ** 2 / (w.numel() * (w * w).sum())) == pytest.approx(0.5, abs=1e-3)


def test_the_polish_takes_each_subjects_least_damping_as_trying_them_in_turn_does():
    """The polish tries its four dampings in one batch. A plain loop, one subject at a time, trying lambda, 10
    lambda, 100 lambda and 1000 lambda in turn and keeping the first whose cost falls (the textbook
    Levenberg-Marquardt step, its Jacobian by forward differences of the state), reaches the same states and
    costs (the polish's Jacobian is in closed form: the two differ in rounding, 1e-7 of a column); two subjects
    start at different distances from the detections' pose, so their dampings and stops differ. A marker on every
    bone, so that every DOF moves one (one that moves none stays put: the test below)."""
    from torchtrack.tracking.epipolar import EpipolarCost
    from torchtrack.tracking.particles import FD_STEP, POLISH_TOL, MarkerAPF

    rig = demo_rig()
    skel = Skeleton.from_urdf().double()
    gen = torch.Generator().manual_seed(5)
    M = 16
    bones = torch.arange(M) % len(skel.bone_names)
    mset = MarkerSet(tuple(f"m{i}" for i in range(M)), bones, 0.05 * torch.randn(M, 3, generator=gen,
                                                                               dtype=torch.float64))
    apf = MarkerAPF([skel, skel], [mset, mset], [rig, rig], APFConfig(polish_steps=8))
    truth = skel.rest_angles().double()
    truth[:3] = torch.tensor([-0.8, 0.1, 0.95])
    X = apf.markers(truth[None])[0]
    P = projection_matrices(rig)
    h = torch.cat([X, torch.ones(M, 1, dtype=torch.float64)], -1)
    uv = torch.einsum("cij,mj->cmi", P, h)
    det = (uv[..., :2] / uv[..., 2:])[:, :, None] + 0.5 * torch.randn(rig.num_cameras, M, 1, 2, generator=gen,
                                                                        dtype=torch.float64)
    score = EpipolarCost(det[None].expand(2, -1, -1, -1, -1), apf.P, apf.F, 20.0)
    start = truth[None] + torch.tensor([[0.02], [0.08]], dtype=torch.float64) * torch.randn(
        2, skel.num_dofs, generator=gen, dtype=torch.float64)
    start = apf.clamp(start)
    got, _ = apf._polish(start, score, torch.ones(2, dtype=torch.bool))

    D = skel.num_dofs
    moves = torch.cat([torch.zeros(1, D, dtype=torch.float64), torch.eye(D, dtype=torch.float64) * FD_STEP])
    for q in range(2):
        def cost(a):
            pts = apf.markers_all(a.expand(2, -1)[:, None])
            return float(score.cost(pts)[q, 0])

        theta, lam, c0 = start[q].clone(), 1e-3, cost(start[q])
        for _ in range(8):
            pts = apf.markers_all(theta.expand(2, -1)[:, None] + moves)
            r = score.residuals(pts)[0][q]  # (D + 1, R)
            J = (r[1:] - r[:1]) / FD_STEP
            A, g = J @ J.T, J @ r[0]
            for _ in range(4):
                trial = apf.clamp((theta + torch.linalg.solve(A + lam * (torch.diag(A.diag()) + 1e-9 * torch.eye(D,
                                   dtype=torch.float64)), -g))[None, None].expand(2, 1, -1))[q, 0]
                c1 = cost(trial)
                if c1 < c0:
                    break
                lam *= 10.0
            else:
                break  # no damping lowered the cost: stop
            done = c0 - c1 < POLISH_TOL * c0
            theta, c0, lam = trial, c1, max(lam / 10.0, 1e-7)
            if done:
                break
        assert cost(got[q]) == pytest.approx(c0, rel=1e-6)
        # the shoulder's three DOFs, which one marker on each arm bone leaves loose, within a tenth of a degree
        torch.testing.assert_close(got[q], theta, rtol=0, atol=2e-3)
    assert float((got[1] - start[1]).abs().max()) > 1e-3  # the far subject did move


def test_the_polishs_jacobian_is_the_markers_derivative_and_holds_dofs_that_move_no_marker():
    """The markers' derivatives by the state in closed form (each DOF turns or slides its subtree) against central
    differences of each subject's forward kinematics, a plain loop over the DOFs, for two subjects in lockstep (bodies
    of other bone lengths, 28 and 13 markers); with no marker on the right foot its ankle moves no marker, and the
    polish leaves it where it started."""
    from torchtrack.tracking.epipolar import EpipolarCost
    from torchtrack.tracking.particles import MarkerAPF

    rig = demo_rig()
    skel = Skeleton.from_urdf().double()
    small = skel.scaled_to_height(1.55).double()
    gen = torch.Generator().manual_seed(8)
    bones = torch.tensor([b for b in range(len(skel.bone_names)) if skel.bone_names[b] != "r_foot"] * 2)
    M = len(bones)
    mset = MarkerSet(tuple(f"m{i}" for i in range(M)), bones, 0.06 * torch.randn(M, 3, generator=gen,
                                                                               dtype=torch.float64))
    few = MarkerSet(mset.names[:13], bones[:13], mset.offset[:13] * 0.8)
    pair = MarkerAPF([skel, small], [mset, few], [rig, rig], APFConfig(polish_steps=8))
    theta = skel.rest_angles().double()
    theta[:3] = torch.tensor([0.3, -0.2, 0.95])
    theta = pair.clamp((theta + 0.3 * torch.randn(2, skel.num_dofs, generator=gen, dtype=torch.float64)))
    R, t, X = pair._links(theta[:, None])
    got = pair._marker_jacobian(R[..., 0], t[..., 0], X[..., 0])  # (2, M, 3, D)
    h = 1e-5
    for q, m in enumerate((M, 13)):
        for d in range(skel.num_dofs):
            step = torch.zeros_like(theta[q])
            step[d] = h
            ref = (pair.markers((theta[q] + step)[None], q) - pair.markers((theta[q] - step)[None], q))[0] / (2 * h)
            torch.testing.assert_close(got[q, :m, :, d], ref, rtol=0, atol=1e-8)
    ankle = skel.dof_names.index("r_ankle_flex")
    assert float(got[..., ankle].abs().max()) == 0.0

    apf = MarkerAPF(skel, mset, rig, APFConfig(polish_steps=8))
    theta = theta[:1]

    X = apf.markers(theta)[0]
    P = projection_matrices(rig)
    uv = torch.einsum("cij,mj->cmi", P, torch.cat([X, torch.ones(M, 1, dtype=torch.float64)], -1))
    det = (uv[..., :2] / uv[..., 2:])[:, :, None]
    start = apf.clamp(theta + 0.05 * torch.randn(theta.shape, generator=gen, dtype=torch.float64))
    out, _ = apf._polish(start, EpipolarCost(det[None], apf.P, apf.F, 20.0), torch.ones(1, dtype=torch.bool))
    assert float(out[0, ankle]) == float(start[0, ankle])
    assert float((out - theta).abs().max()) < float((start - theta).abs().max())


def test_bad_filter_settings_are_refused():
    with pytest.raises(InputError):
        APFConfig(survival=1.5)
    with pytest.raises(InputError):
        APFConfig(particles=1)
    with pytest.raises(InputError, match="polish"):
        APFConfig(polish="reproject")


def test_marker_set_recovers_known_markers():
    """Markers placed on known bones at known offsets, poses random within the limits: each marker is given back
    to its bone at its offset, and the poses fitted to the markers from a perturbed start find them again."""
    skel = Skeleton.from_urdf().double()
    gen = torch.Generator().manual_seed(4)
    T, M = 12, 9
    D = skel.num_dofs
    rest = skel.rest_angles().double()
    angles = rest + 1.0 * (torch.rand(T, D, generator=gen, dtype=torch.float64) - 0.5)
    angles[:, 3] = torch.rand(T, generator=gen, dtype=torch.float64) * 6  # any heading
    angles = skel.clamp(angles)
    bones = torch.tensor([0, 1, 2, 3, 4, 9, 10, 12, 14])
    offsets = 0.06 * torch.randn(M, 3, generator=gen, dtype=torch.float64)
    truth = MarkerSet(tuple(f"m{i}" for i in range(M)), bones, offsets)
    markers = truth.positions(skel.forward(angles).bone_frames)
    markers[3, 2] = math.nan  # a missing sample
    found, spread = assign_markers(skel, angles, markers, truth.names)
    assert torch.equal(found.bone, bones)
    torch.testing.assert_close(found.offset.double(), offsets, atol=1e-5, rtol=0)
    assert float(spread.max()) < 1e-5
    start = skel.clamp(angles + 0.05 * torch.randn(T, D, generator=gen, dtype=torch.float64))
    fitted_set, fitted = fit_marker_set(skel, start, markers, truth.names, rounds=2)
    err = (fitted_set.positions(skel.forward(fitted).bone_frames) - markers).norm(dim=-1)
    assert float(err.nanmean()) < 0.01
    with pytest.raises(InputError, match="m0"):
        bad = markers.clone()
        bad[1:, 0] = math.nan
        assign_markers(skel, angles, bad, truth.names)


def test_still_start_gives_each_marker_the_bone_whose_flesh_holds_it():
    """A subject holding still (only the root moves): a marker moves with every bone equally rigidly, so the least
    spread alone cannot tell its bone (every spread ties; it takes the first bone). Each marker placed just outside
    the middle of one blob's side (the blob's own ellipsoid, independent of the rule's code), 2 mm of triangulation
    noise: each goes to that blob's bone, at its offset within a few mm."""
    from torchtrack.blobs.model import BlobModel

    skel = Skeleton.from_urdf().double()
    blobs = BlobModel.from_config(skel)
    gen = torch.Generator().manual_seed(9)
    T = 20
    angles = skel.rest_angles().double().repeat(T, 1)
    angles[:, :2] += 0.3 * torch.randn(T, 2, generator=gen, dtype=torch.float64)  # the body moved about, still
    angles[:, 3] += 0.5 * torch.randn(T, generator=gen, dtype=torch.float64)
    names = ("l_thigh", "r_shank", "l_upperarm", "r_forearm", "chest", "pelvis", "head", "l_foot")
    k = torch.tensor([blobs.names.index(n) for n in names])
    # 5 % out of the blob's front, at its middle (a side of the template's wide pelvis lies in the hanging hands')
    side = torch.tensor([0.0, 1.05, 0.0], dtype=torch.float64)
    offsets = blobs.offset_local[k].double() + (blobs.R_bone_blob[k].double() @ (blobs.semi_axes[k].double()
                                                                                  * side)[..., None])[..., 0]
    truth = MarkerSet(names, blobs.bone_of_blob[k], offsets)
    markers = truth.positions(skel.forward(angles).bone_frames)
    markers = markers + 0.002 * torch.randn(markers.shape, generator=gen, dtype=torch.float64)
    found, _ = assign_markers(skel, angles, markers, names)
    assert [skel.bone_names[b] for b in found.bone] == [skel.bone_names[b] for b in truth.bone]
    torch.testing.assert_close(found.offset.double(), offsets, atol=3e-3, rtol=0)


def test_the_refit_along_a_track_places_markers_the_first_seconds_placed_poorly():
    """A body moving through poses (its "track"), each marker just outside the middle of one blob's side, 2 mm of
    triangulation noise. The first fit put every marker 3 cm off and the right thigh's on the pelvis (where the
    first frame has it, as a still start does); on 5 frames two markers' detections are swapped (linked to the
    wrong label, over 20 cm away). Refitted along the track, each marker is back on its blob's bone at its offset
    within a few mm: the gate kept the swapped detections out. A marker placed by too few frames keeps its first
    fit."""
    from pathlib import Path

    from torchtrack.blobs.model import BlobModel
    from torchtrack.io.poses import Poses
    from torchtrack.markers.track import REFIT_MIN_FRAMES, MarkerSequence, refit_marker_set

    skel = Skeleton.from_urdf().double()
    blobs = BlobModel.from_config(skel)
    gen = torch.Generator().manual_seed(11)
    T, D = 40, skel.num_dofs
    # from the rest pose to another and back, a random wiggle on the way
    ramp = torch.sin(torch.linspace(0, math.pi, T, dtype=torch.float64))[:, None]
    turn = 1.6 * (torch.rand(D, generator=gen, dtype=torch.float64) - 0.5)
    angles = skel.clamp(skel.rest_angles().double() + ramp * turn
                        + 0.1 * torch.randn(T, D, generator=gen, dtype=torch.float64))
    names = ("l_thigh", "r_shank", "l_upperarm", "r_forearm", "chest", "r_thigh", "head", "l_foot", "pelvis")
    M = len(names)
    k = torch.tensor([blobs.names.index(n) for n in names])
    side = torch.tensor([0.0, 1.05, 0.0], dtype=torch.float64)
    offsets = blobs.offset_local[k].double() + (blobs.R_bone_blob[k].double() @ (blobs.semi_axes[k].double()
                                                                                  * side)[..., None])[..., 0]
    bones = blobs.bone_of_blob[k]
    X = MarkerSet(names, bones, offsets).positions(skel.forward(angles).bone_frames)
    X = X + 0.002 * torch.randn(X.shape, generator=gen, dtype=torch.float64)
    frames = ((X[:, 1] - X[:, 7]).norm(dim=-1) > 0.2).nonzero()[:5, 0]
    X[frames, 1], X[frames, 7] = X[frames, 7].clone(), X[frames, 1].clone()
    X[REFIT_MIN_FRAMES - 1:, 8] = math.nan  # the last marker seen on too few frames
    first_offsets = offsets + 0.03 / math.sqrt(3)
    pelvis = skel.forward(angles[:1]).bone_frames[0, skel.bone_names.index("pelvis")]
    first_offsets[5] = pelvis[:3, :3].T @ (X[0, 5] - pelvis[:3, 3])
    first_bones = torch.where(torch.arange(M) == 5, skel.bone_names.index("pelvis"), bones)
    first = MarkerSet(names, first_bones, first_offsets)
    seq = MarkerSequence(Path("walk"), None, 0, None, None, X, skel, first, angles[0], torch.arange(M), 0.0)
    poses = Poses(30.0, np.arange(T), [], np.zeros((T, 0, 3), np.float32), list(skel.dof_names), angles.numpy(),
                  np.ones(T, bool), np.zeros((T, 0), np.float32))
    got = refit_marker_set(seq, poses, 0.1).marker_set
    assert [skel.bone_names[b] for b in got.bone[:8]] == [skel.bone_names[b] for b in bones[:8]]
    torch.testing.assert_close(got.offset[:8].double(), offsets[:8], atol=4e-3, rtol=0)
    assert int(got.bone[8]) == int(first.bone[8])
    torch.testing.assert_close(got.offset[8].double(), first.offset[8].double())


def test_mmta_and_mmtp_against_a_plain_loop():
    from torchtrack.eval.metrics import evaluate
    from torchtrack.io.poses import Poses

    rng = np.random.default_rng(6)
    T, M, J = 5, 4, 16
    from torchtrack.conventions import LANDMARKS

    def poses(markers, names):
        return Poses(30.0, np.arange(T), list(LANDMARKS), np.zeros((T, J, 3), np.float32), ["x"],
                     np.zeros((T, 1), np.float32), np.ones(T, bool), np.ones((T, J), np.float32),
                     marker_names=names, markers3d=markers.astype(np.float32))
    truth = rng.normal(size=(T, M, 3))
    truth[2, 1] = np.nan  # the truth lacks one sample
    pred = truth + rng.normal(scale=0.04, size=(T, M, 3))
    pred[3, 0] = np.nan  # the prediction lacks one: a miss
    names = ["a", "b", "c", "d"]
    rep = evaluate(poses(pred[:, ::-1], names[::-1]), poses(truth, names), marker_threshold_m=0.05).markers
    shares, precs = [], []
    for t in range(T):
        hits, errs, total = 0, [], 0
        for m in range(M):
            if not np.isfinite(truth[t, m]).all():
                continue
            total += 1
            e = np.linalg.norm(pred[t, m] - truth[t, m])
            if np.isfinite(e) and e <= 0.05:
                hits += 1
                errs.append(e)
        shares.append(hits / total)
        if errs:
            precs.append(np.mean(errs))
    assert rep.mmta == pytest.approx(np.mean(shares)) and rep.mmtp_mm == pytest.approx(1000 * np.mean(precs))
    assert rep.markers == 4 and rep.frames == T


def test_markers_the_prediction_does_not_name_are_said_and_left_out(caplog):
    """A ground truth with markers the track does not name (a marker set that does not match): a warning names
    them, and MMTA is over the markers both name, as a plain loop over those gives it."""
    from torchtrack.conventions import LANDMARKS
    from torchtrack.eval.metrics import evaluate
    from torchtrack.io.poses import Poses

    T, J = 3, 16
    truth = np.random.default_rng(7).normal(size=(T, 3, 3))
    pred = truth[:, :2] + np.array([0.0, 0.0, 0.03])  # the first two within 5 cm
    pred[1, 1] += 0.1  # one miss

    def poses(markers, names):
        return Poses(30.0, np.arange(T), list(LANDMARKS), np.zeros((T, J, 3), np.float32), ["x"],
                     np.zeros((T, 1), np.float32), np.ones(T, bool), np.ones((T, J), np.float32),
                     marker_names=names, markers3d=markers.astype(np.float32))
    with caplog.at_level("WARNING"):
        rep = evaluate(poses(pred, ["LASI", "RASI"]), poses(truth, ["LASI", "RASI", "LFHD"])).markers
    assert "['LFHD']" in caplog.text
    assert rep.markers == 2 and rep.mmta == pytest.approx((1 + 0.5 + 1) / 3)


def test_track_markers_follows_a_simulated_capture(tmp_path, capsys):
    """`torchtrack track` on a simulated Plug-in-Gait capture (real markers, the real 4-camera rig, misses, false
    detections and noise) picks marker mode, fits the subject from the triangulated detections alone and tracks
    it: the markers against the capture's own."""
    from torchtrack.cli import main

    cap, out = tmp_path / "cap", tmp_path / "track"
    pig = shared_data("mocap", "btk", "c3d", "PiG_Motion-FlatFoot-Full.c3d")
    assert main(["synth", "markers", "--motion", str(pig), "--calibration", str(shared_data(*DEMO_RIG)), "--out", str(cap),
                 "--duration", "1.2"]) == 0
    assert main(["track", str(cap), "--out", str(out)]) == 0
    assert main(["eval", str(out / "poses.npz"), str(cap / "gt.npz")]) == 0
    text = capsys.readouterr().out
    mmta = float(text.split("MMTA@50mm")[1].split("%")[0])
    mmtp = float(text.split("MMTP")[1].split()[0])
    assert mmta >= 95.0 and mmtp <= 15.0, text
    from test_docs import documented_keys

    for f in (out / "poses.npz", cap / "gt.npz"):  # every key the marker mode writes is in docs/formats.md
        with np.load(f) as z:
            assert set(z.files) <= documented_keys("`poses.npz`"), (f, z.files)


def test_triangulation_ignores_false_candidates():
    """Points seen by every view with a false candidate beside each true one: the triangulation finds the points
    (against their truth) and says how many views agree; a marker in one view only is NaN."""
    from torchtrack.markers.triangulate import triangulate_candidates

    rig = demo_rig()
    gen = torch.Generator().manual_seed(7)
    T, M, C = 3, 5, rig.num_cameras
    X = torch.rand(T, M, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.5, 1.0, 1.6]) + torch.tensor(
        [-1.6, -0.5, 0.2])
    P = projection_matrices(rig)
    h = torch.cat([X, torch.ones(T, M, 1, dtype=torch.float64)], -1)
    uv = torch.einsum("cij,tmj->tcmi", P, h)
    uv = uv[..., :2] / uv[..., 2:]  # (T, C, M, 2)
    false = uv + torch.tensor([150.0, -90.0], dtype=torch.float64)
    det = torch.stack([false, uv + 0.5 * torch.randn(T, C, M, 2, generator=gen, dtype=torch.float64)], 3)
    det[:, 1:, 0] = math.nan  # marker 0 in view 0 only
    det[:, 2, 1] = math.nan  # marker 1 not in view 2
    got, views = triangulate_candidates(det, P)
    assert torch.isnan(got[:, 0]).all() and (views[:, 0] == 0).all()
    assert float((got[:, 1:] - X[:, 1:]).norm(dim=-1).max()) < 0.01
    assert (views[:, 1] == C - 1).all() and (views[:, 2:] == C).all()
    chunked, _ = triangulate_candidates(det, P, chunk=2)  # frames in chunks: the same points
    torch.testing.assert_close(chunked, got, equal_nan=True)


def _walk_frame(tmp_path, t: int = 20):
    """The Plug-in-Gait walk simulated in the demo rig (no misses or false detections, 1 px noise), its subject
    fitted from the capture's markers, and frame ``t``: the filter, the subject's skeleton, marker set and poses,
    the capture's markers ``(T, M, 3)`` and the frame's triangulated markers ``(1, M, 3)``."""
    from torchtrack.cli import main
    from torchtrack.io.markers2d import load_markers2d
    from torchtrack.io.poses import load_poses
    from torchtrack.markers.model import subject_from_markers
    from torchtrack.markers.triangulate import triangulate_candidates
    from torchtrack.tracking.particles import MarkerAPF

    cap = tmp_path / "cap"
    pig = shared_data("mocap", "btk", "c3d", "PiG_Motion-FlatFoot-Full.c3d")
    assert main(["synth", "markers", "--motion", str(pig), "--calibration", str(shared_data(*DEMO_RIG)), "--out",
                 str(cap), "--duration", "1.0", "--p-miss", "0", "--false-rate", "0", "--sigma", "1"]) == 0
    rig = load_calibration(cap / "calibration.toml", warn_units=False).double()
    det, gt = load_markers2d(cap / "markers2d.npz"), load_poses(cap / "gt.npz")
    m3 = torch.from_numpy(gt.markers3d.astype(np.float64))
    skel, mset, angles = subject_from_markers(m3, gt.marker_names, gt.fps)
    z = pinhole_pixels(rig, torch.from_numpy(det.uv[t].astype(np.float64)))
    X, _ = triangulate_candidates(z[None], projection_matrices(rig))
    return MarkerAPF(skel, mset, rig), skel, mset, angles, m3, X


def test_a_lost_filter_is_started_again_from_the_markers(tmp_path):
    """A filter whose estimate is a body turned round 1 m away: the lost test fires, and the restart from the
    frame's triangulated markers lands on the body (the markers within 3 cm of the capture's)."""
    from torchtrack.markers.track import _lost, _restart

    t = 20
    apf, skel, mset, angles, m3, X = _walk_frame(tmp_path, t)
    assert not bool(_lost(apf, angles[t][None], X)[0])
    wrong = angles[t].clone()
    wrong[0] += 1.0
    wrong[3] += math.pi
    assert bool(_lost(apf, wrong[None], X)[0])
    found = _restart(apf, 0, wrong, X[0], angles[0])
    err = (apf.markers(found[None])[0] - m3[t]).norm(dim=-1)
    assert float(err.mean()) < 0.03


def test_a_limb_left_elsewhere_or_a_body_a_few_cm_off_is_lost_too(tmp_path):
    """Two losses the share of far markers misses (fewer than 30 % of the triangulated markers over 10 cm off, counted
    by a plain loop): an arm bent 1.5 rad away from the capture's, and the whole body 6 cm off. Both are lost (the
    limb's markers mostly far; the markers' median distance over 4 cm), the true pose and one 1 cm off are not, and
    the restart from the arm's estimate brings the arm back (its markers within 3 cm of the capture's)."""
    from torchtrack.markers.track import _lost, _restart

    t = 20
    apf, skel, mset, angles, m3, X = _walk_frame(tmp_path, t)

    def far_share(a):  # a plain loop over the triangulated markers
        model, n, far = apf.markers(a[None])[0], 0, 0
        for m in range(X.shape[1]):
            if bool(torch.isfinite(X[0, m]).all()):
                n += 1
                far += float((model[m] - X[0, m]).norm()) > 0.1
        return far / n

    names = list(skel.dof_names)
    arm = angles[t].clone()
    arm[names.index("r_shoulder_flex")] += 1.5
    arm[names.index("r_elbow_flex")] = 0.0
    arm = skel.clamp(arm[None])[0]
    shifted, near = angles[t].clone(), angles[t].clone()
    shifted[0] += 0.06
    near[0] += 0.01
    for a, lost in ((angles[t], False), (near, False), (arm, True), (shifted, True)):
        assert far_share(a) < 0.3
        assert bool(_lost(apf, a[None], X)[0]) == lost
    found = _restart(apf, 0, arm, X[0], angles[0])
    on_arm = [i for i, n in enumerate(mset.names) if n.startswith(("RSHO", "RUPA", "RELB", "RFRA", "RWR", "RFIN"))]
    assert len(on_arm) >= 3
    err = (apf.markers(found[None])[0, on_arm] - m3[t, on_arm]).norm(dim=-1)
    assert float(err.mean()) < 0.03, err


def test_frames_without_detections_are_invalid_and_the_track_goes_on(tmp_path):
    """Frames whose detections are all gone (NaN): marked invalid, the filter holds and tracks the frames after."""
    from torchtrack.cli import main
    from torchtrack.io.markers2d import load_markers2d, save_markers2d
    from torchtrack.io.poses import load_poses
    from torchtrack.markers.track import track_markers

    cap = tmp_path / "cap"
    pig = shared_data("mocap", "btk", "c3d", "PiG_Motion-FlatFoot-Full.c3d")
    assert main(["synth", "markers", "--motion", str(pig), "--calibration", str(shared_data(*DEMO_RIG)), "--out", str(cap),
                 "--duration", "1.2"]) == 0
    det = load_markers2d(cap / "markers2d.npz")
    det.uv[30:32] = np.nan
    save_markers2d(det, cap / "markers2d.npz")
    poses = track_markers(cap, progress=False).poses
    gt = load_poses(cap / "gt.npz")
    assert poses.valid.tolist() == [t not in (30, 31) for t in range(len(poses.valid))]
    err = np.linalg.norm(poses.markers3d[33:] - gt.markers3d[33:], axis=-1)
    assert float(np.nanmean(err)) < 0.03


def test_sequences_tracked_in_lockstep_get_their_tracks_alone(tmp_path):
    """Three simulated captures tracked in lockstep (one filter, each frame one batched step over the sequences and
    their particles): one with frames of no detections, one shorter whose body jumps 1.9 m halfway (a restart),
    one in a rig of five cameras with fewer markers (the others' views and markers padded). Each gets the track it
    gets alone: the same invalid frames and restarts, and the same markers on most frames (each sequence draws from
    its own generator; where the padding changes a sum in the last place and that flips a resampling draw, a frame's
    markers differ by millimetres: at most 1 cm, under 1 mm on 3 frames in 4; where it moves the lost-track test
    across its threshold, the restart comes a frame earlier or later and the tracks agree again two frames after it),
    and follows its capture's markers."""
    from torchtrack.cameras import CameraRig, save_calibration
    from torchtrack.cli import main
    from torchtrack.io.markers2d import load_markers2d, save_markers2d
    from torchtrack.io.poses import load_poses
    from torchtrack.markers.track import load_marker_sequence, track_marker_sequences, track_markers

    rig = demo_rig().double()
    # a fifth camera: the first one turned 90 degrees about the vertical through the cameras' centre
    c = (-rig.R_cam_world.mT @ rig.t_cam_world[..., None])[..., 0].mean(0)
    turn = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    R5 = rig.R_cam_world[0] @ turn.T
    t5 = rig.t_cam_world[0] + rig.R_cam_world[0] @ (c - turn.T @ c)
    five = CameraRig(list(rig.names) + ["turned"], torch.cat([rig.K, rig.K[:1]]),
                     torch.cat([rig.R_cam_world, R5[None]]), torch.cat([rig.t_cam_world, t5[None]]),
                     torch.cat([rig.image_size_wh, rig.image_size_wh[:1]]), torch.cat([rig.dist, rig.dist[:1]]))
    save_calibration(five, tmp_path / "five.toml")
    pig = shared_data("mocap", "btk", "c3d", "PiG_Motion-FlatFoot-Full.c3d")
    for name, seconds, calib in (("held", 1.2, shared_data(*DEMO_RIG)), ("jump", 2.6, shared_data(*DEMO_RIG)),
                                 ("five", 1.0, tmp_path / "five.toml")):
        assert main(["synth", "markers", "--motion", str(pig), "--calibration", str(calib),
                     "--out", str(tmp_path / name), "--duration", str(seconds), "--starfish", "0"]) == 0
    held = load_markers2d(tmp_path / "held" / "markers2d.npz")
    held.uv[10:12] = np.nan
    save_markers2d(held, tmp_path / "held" / "markers2d.npz")
    jump = load_markers2d(tmp_path / "jump" / "markers2d.npz")
    spliced = np.r_[0:12, 60:78]  # 48 frames left out: the body 1.9 m on at frame 12 (0.7 m the filter follows)
    jump.uv, jump.frame_index = jump.uv[spliced], np.arange(len(spliced))
    jump.extra = {k: v[spliced] for k, v in jump.extra.items()}
    save_markers2d(jump, tmp_path / "jump" / "markers2d.npz")
    five = load_markers2d(tmp_path / "five" / "markers2d.npz")
    kept = [i for i, n in enumerate(five.marker_names) if n not in ("T10", "RBAK")]
    five.uv, five.marker_names = five.uv[:, :, kept], [five.marker_names[i] for i in kept]
    save_markers2d(five, tmp_path / "five" / "markers2d.npz")
    cfg = APFConfig(particles=200)
    names = ("held", "jump", "five")
    together = track_marker_sequences([load_marker_sequence(tmp_path / n) for n in names], cfg, progress=False)
    for name, lockstep in zip(names, together):
        alone = track_markers(tmp_path / name, cfg, progress=False).poses
        got = lockstep.poses
        assert got.angles.shape == alone.angles.shape and got.marker_names == alone.marker_names
        # the filter's markers (the output's measured ones are the same triangulations either way)
        apart = np.nanmean(np.linalg.norm(got.extra["markers3d_body"] - alone.extra["markers3d_body"], axis=-1), 1)
        assert got.valid.tolist() == alone.valid.tolist()
        assert got.valid.tolist() == [name != "held" or t not in (10, 11) for t in range(len(got.valid))]
        restarts = got.extra["reinitialised"]
        # a restart decision the rounding moves across its threshold: the two restart at most a frame apart, and
        # agree again two frames after
        mine, its = np.flatnonzero(restarts), np.flatnonzero(alone.extra["reinitialised"])
        assert len(mine) == len(its) and np.all(np.abs(mine - its) <= 1), (name, mine, its)
        settling = np.zeros(len(apart), dtype=bool)
        for t in np.concatenate([mine, its]):
            settling[t:t + 2] = True
        assert float(apart[~settling].max()) < 0.01 and float(np.mean(apart < 1e-3)) >= 0.75, (name, apart)
        # the jump restarts there; the held sequence may restart only just after its held frames (a leg that moved
        # meanwhile and that the filter did not catch up is a limb lost); the other never
        assert bool(restarts[12:15].any()) or name != "jump", (name, restarts)
        assert not (restarts[:12].any() or restarts[15:].any()) and (name != "five" or not restarts.any()), (
            name, restarts)
        gt = load_poses(tmp_path / name / "gt.npz")
        truth = gt.markers3d[spliced] if name == "jump" else gt.markers3d
        idx = [list(gt.marker_names).index(n) for n in got.marker_names]
        err = np.linalg.norm(got.markers3d - truth[:, idx], axis=-1)[got.valid]
        assert float(np.nanmean(err)) < 0.03


def test_track_several_marker_folders_in_lockstep(tmp_path, capsys):
    """`torchtrack track A B C --out DIR` on marker folders: one run in lockstep writes DIR/<name>/poses.npz for each
    that can be read, each within 15 mm of its capture's markers; a folder with a broken markers2d.npz is reported
    by name, exit 1, its earlier output left as it was; marker and video folders in one run, or --batch-size 0, are
    refused before any work."""
    from torchtrack.cli import main
    from torchtrack.io.poses import load_poses

    pig = shared_data("mocap", "btk", "c3d", "PiG_Motion-FlatFoot-Full.c3d")
    for name, seconds in (("walk_a", 1.0), ("walk_b", 0.8)):
        assert main(["synth", "markers", "--motion", str(pig), "--calibration", str(shared_data(*DEMO_RIG)),
                     "--out", str(tmp_path / name), "--duration", str(seconds)]) == 0
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "calibration.toml").write_text((tmp_path / "walk_a" / "calibration.toml").read_text())
    (broken / "markers2d.npz").write_bytes(b"not an npz")
    out = tmp_path / "tracks"
    capsys.readouterr()
    code = main(["track", str(tmp_path / "walk_a"), str(broken), str(tmp_path / "walk_b"), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and "broken" in err and "1 of 3 sequences failed" in err, err
    assert not (out / "broken" / "poses.npz").exists()
    for name in ("walk_a", "walk_b"):
        got, truth = load_poses(out / name / "poses.npz"), load_poses(tmp_path / name / "gt.npz")
        assert got.valid.all() and got.num_frames == truth.num_frames
        assert float(np.nanmean(np.linalg.norm(got.markers3d - truth.markers3d, axis=-1))) < 0.015
        assert (out / name / "tb").is_dir()
    # again over the same outputs, walk_b now broken: its earlier track stays as it was, walk_a's is replaced
    before = (out / "walk_b" / "poses.npz").read_bytes()
    (tmp_path / "walk_b" / "markers2d.npz").write_bytes(b"broken too")
    code = main(["track", str(tmp_path / "walk_a"), str(tmp_path / "walk_b"), "--out", str(out), "--overwrite"])
    assert code == 1 and "walk_b: failed" in capsys.readouterr().err
    assert (out / "walk_b" / "poses.npz").read_bytes() == before
    assert load_poses(out / "walk_a" / "poses.npz").valid.all()
    video = tmp_path / "video"
    video.mkdir()
    code = main(["track", str(tmp_path / "walk_a"), str(video), "--out", str(tmp_path / "mixed")])
    assert code == 2 and "separate runs" in capsys.readouterr().err
    code = main(["track", str(tmp_path / "walk_a"), "--out", str(tmp_path / "mixed"), "--batch-size", "0"])
    assert code == 2 and "--batch-size must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "mixed").exists()
