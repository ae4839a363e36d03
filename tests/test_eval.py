"""Pose accuracy metrics against plain-Python references, and `torchtrack eval` end to end."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

from torchtrack.checks import InputError, ShapeError
from torchtrack.cli import main
from torchtrack.conventions import LANDMARKS
from torchtrack.eval import evaluate, match_frames, mpjpe, pck
from torchtrack.io.poses import Poses, load_poses, save_poses


def make_poses(joints3d: np.ndarray, frame_index=None, valid=None, names=LANDMARKS, extra=None) -> Poses:
    T, J = joints3d.shape[:2]
    return Poses(fps=30.0, frame_index=np.arange(T) if frame_index is None else np.asarray(frame_index),
                 joint_names=list(names), joints3d=joints3d.astype(np.float32), dof_names=["root_x"],
                 angles=np.zeros((T, 1), np.float32), valid=np.ones(T, bool) if valid is None else np.asarray(valid),
                 confidence=np.ones((T, J), np.float32), extra=extra or {})


def random_pair(T=6, J=5, seed=0, noise=0.08):
    rng = np.random.default_rng(seed)
    truth = rng.normal(size=(T, J, 3))
    pred = truth + rng.normal(scale=noise, size=(T, J, 3))
    return pred, truth


def loop_errors(pred, truth, mask):
    """Plain-Python reference: {(t, j): error} over masked frames and finite reference joints."""
    out = {}
    for t in range(pred.shape[0]):
        if not mask[t]:
            continue
        for j in range(pred.shape[1]):
            q = [float(v) for v in truth[t, j]]
            if any(math.isnan(v) for v in q):
                continue
            out[t, j] = math.sqrt(sum((float(a) - b) ** 2 for a, b in zip(pred[t, j], q)))
    return out


def loop_mean(values):
    values = list(values)
    return sum(values) / len(values) if values else float("nan")


def test_mpjpe_matches_loop_reference():
    pred, truth = random_pair(T=7, J=5)
    truth[1, 2] = np.nan
    truth[4, :, 0] = np.nan  # a frame without any reference joint
    truth[:, 3, 1] = np.nan  # a joint never in the reference
    mask = np.array([True, True, False, True, True, True, False])
    ref = loop_errors(pred, truth, mask)
    res = mpjpe(pred, truth, mask)
    assert res.per_joint.shape == (5,) and res.per_frame.shape == (7,)
    for j in range(5):
        np.testing.assert_allclose(res.per_joint[j], loop_mean(e for (_, jj), e in ref.items() if jj == j))
    for t in range(7):
        np.testing.assert_allclose(res.per_frame[t], loop_mean(e for (tt, _), e in ref.items() if tt == t))
    np.testing.assert_allclose(res.mean, loop_mean(ref.values()))
    assert np.isnan(res.per_joint[3]) and np.isnan(res.per_frame[4]) and np.isnan(res.per_frame[2])


def test_nan_reference_joint_changes_nothing_else():
    pred, truth = random_pair()
    full = mpjpe(pred, truth)
    truth[2, 1] = np.nan
    res = mpjpe(pred, truth)
    np.testing.assert_allclose(np.delete(res.per_joint, 1), np.delete(full.per_joint, 1))
    errs = np.linalg.norm(pred[2] - truth[2], axis=-1)
    np.testing.assert_allclose(res.per_frame[2], np.delete(errs, 1).mean())


def test_pck_matches_loop_reference():
    pred, truth = random_pair(T=8, J=6, noise=0.07, seed=3)
    truth[0, 0] = np.nan
    mask = np.arange(8) != 5
    ref = loop_errors(pred, truth, mask)
    thresholds = [0.05, 0.1, 0.15]
    got = pck(pred, truth, mask, thresholds)
    assert got.shape == (3,)
    for th, frac in zip(thresholds, got):
        np.testing.assert_allclose(frac, sum(e <= th for e in ref.values()) / len(ref))
    one = pck(pred, truth, mask)  # default 0.1 m, one threshold: a 0-d result
    assert np.shape(one) == () and float(one) == pytest.approx(got[1])
    assert 0 < got[0] < got[1] < got[2] <= 1


def test_nothing_to_evaluate_is_nan_without_warnings():
    pred, truth = random_pair()
    mask = np.zeros(pred.shape[0], bool)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = mpjpe(pred, truth, mask)
        frac = pck(pred, truth, mask, [0.1, 0.2])
    assert np.isnan(res.mean) and np.isnan(res.per_joint).all() and np.isnan(frac).all()


def test_bad_input():
    pred, truth = random_pair()
    with pytest.raises(ShapeError, match="T, J, 3"):
        mpjpe(pred, truth[:, :3])
    with pytest.raises(ShapeError, match="mask"):
        mpjpe(pred, truth, np.ones(3, bool))
    with pytest.raises(InputError, match="thresholds"):
        pck(pred, truth, thresholds_m=[0.1, -0.05])
    pred[1, 1, 1] = np.nan
    with pytest.raises(InputError, match="pred"):
        mpjpe(pred, truth)
    mask = np.ones(pred.shape[0], bool)
    mask[1] = False
    assert np.isfinite(mpjpe(pred, truth, mask).mean)  # NaN only in a frame not evaluated


def test_match_frames_with_shifted_and_unsorted_frame_index():
    truth = make_poses(np.zeros((25, 16, 3)), frame_index=np.arange(25))
    pred = make_poses(np.zeros((20, 16, 3)), frame_index=np.arange(10, 30)[::-1])
    pi, ti = match_frames(pred, truth)
    np.testing.assert_array_equal(truth.frame_index[ti], np.arange(10, 25))
    np.testing.assert_array_equal(pred.frame_index[pi], truth.frame_index[ti])


def test_match_frames_errors_name_both():
    a = make_poses(np.zeros((3, 16, 3)), frame_index=[0, 1, 2])
    b = make_poses(np.zeros((3, 16, 3)), frame_index=[7, 8, 9])
    with pytest.raises(InputError, match=r"pred\.npz.*0\.\.2.*gt\.npz.*7\.\.9"):
        match_frames(a, b, "pred.npz", "gt.npz")
    c = make_poses(np.zeros((3, 16, 3)), frame_index=[0, 1, 1])
    with pytest.raises(InputError, match="gt.npz.*repeats frame 1"):
        match_frames(a, c, "pred.npz", "gt.npz")


def test_evaluate_shifted_frames_compares_same_frame_numbers():
    rng = np.random.default_rng(1)
    truth_xyz = rng.normal(size=(30, 16, 3))
    offsets = np.linspace(0.01, 0.2, 30)  # frame t: every joint off by offsets[t] along x
    pred_xyz = truth_xyz[5:25] + np.stack([offsets[5:25], 0 * offsets[5:25], 0 * offsets[5:25]], -1)[:, None]
    truth = make_poses(truth_xyz)
    pred = make_poses(pred_xyz, frame_index=np.arange(5, 25))
    rep = evaluate(pred, truth)
    assert rep.frames_evaluated == 20 and rep.frames_truth_only == 10 and rep.frames_lost == 0
    np.testing.assert_array_equal(rep.frame_index, np.arange(5, 25))
    np.testing.assert_allclose(rep.per_frame_mm, 1000 * offsets[5:25], rtol=1e-5)
    np.testing.assert_allclose(rep.mpjpe_mm, 1000 * offsets[5:25].mean(), rtol=1e-5)
    np.testing.assert_allclose(rep.per_landmark_mm, 1000 * offsets[5:25].mean(), rtol=1e-5)
    np.testing.assert_allclose(rep.median_frame_mm, 1000 * np.median(offsets[5:25]), rtol=1e-5)
    assert rep.max_frame == 24 and rep.max_frame_mm == pytest.approx(1000 * offsets[24], rel=1e-5)
    assert rep.root_aligned_mpjpe_mm == pytest.approx(0, abs=1e-3)  # a pure translation
    expect = [(offsets[5:25] <= t).mean() for t in (0.05, 0.1, 0.15)]
    np.testing.assert_allclose(rep.pck, expect)


def test_invalid_prediction_frames_are_lost_not_errors():
    pred_xyz, truth_xyz = random_pair(T=10, J=16, seed=4)
    valid = np.ones(10, bool)
    valid[[2, 7]] = False
    pred_xyz[~valid] = np.nan  # a lost tracker writes no estimate
    truth_valid = np.ones(10, bool)
    truth_valid[4] = False  # no reference here: neither lost nor evaluated
    truth_xyz[4] = np.nan
    rep = evaluate(make_poses(pred_xyz, valid=valid), make_poses(truth_xyz, valid=truth_valid))
    keep = valid & truth_valid
    assert rep.frames_lost == 2 and rep.frames_evaluated == 7 and rep.frames_without_reference == 1
    assert rep.lost_fraction == pytest.approx(2 / 9)
    np.testing.assert_array_equal(rep.lost_frame_index, [2, 7])
    np.testing.assert_array_equal(rep.frame_index, np.flatnonzero(keep))
    errs = np.linalg.norm(pred_xyz[keep] - truth_xyz[keep], axis=-1)  # (7, 16)
    np.testing.assert_allclose(rep.mpjpe_mm, 1000 * errs.mean(), rtol=1e-5)
    np.testing.assert_allclose(rep.per_landmark_mm, 1000 * errs.mean(0), rtol=1e-5)
    aligned = np.linalg.norm((pred_xyz[keep] - pred_xyz[keep][:, :1]) - (truth_xyz[keep] - truth_xyz[keep][:, :1]),
                             axis=-1)[:, 1:]
    np.testing.assert_allclose(rep.root_aligned_mpjpe_mm, 1000 * aligned.mean(), rtol=1e-5)
    np.testing.assert_allclose(rep.pck, [(errs <= t).mean() for t in (0.05, 0.1, 0.15)])


def test_all_frames_lost_report_is_readable_and_valid_json():
    pred_xyz, truth_xyz = random_pair(T=4, J=16)
    rep = evaluate(make_poses(pred_xyz, valid=np.zeros(4, bool)), make_poses(truth_xyz))
    assert rep.frames_lost == 4 and rep.frames_evaluated == 0 and rep.max_frame is None
    assert "n/a" in rep.format()
    doc = json.loads(json.dumps(rep.to_dict(), allow_nan=False))
    assert doc["mpjpe_mm"] is None and doc["frames_lost"] == 4 and doc["lost_fraction"] == 1.0


def test_evaluate_landmark_subset_and_missing_names():
    pred_xyz, truth_xyz = random_pair(T=5, J=16)
    rep = evaluate(make_poses(pred_xyz), make_poses(truth_xyz), landmarks=["l_wrist", "r_wrist"])
    assert rep.landmark_names == ["l_wrist", "r_wrist"]
    errs = np.linalg.norm(pred_xyz[:, [6, 9]] - truth_xyz[:, [6, 9]], axis=-1)
    np.testing.assert_allclose(rep.per_landmark_mm, 1000 * errs.mean(0), rtol=1e-5)
    with_nose = make_poses(np.concatenate([pred_xyz, pred_xyz[:, 3:4]], 1), names=list(LANDMARKS) + ["nose"])
    with pytest.raises(InputError, match=r"gt\.npz.*nose"):  # the reference lacks it
        evaluate(with_nose, make_poses(truth_xyz), landmarks=["nose"], truth_name="gt.npz")


def test_gt_with_extra_keys_loads_and_evaluates(tmp_path):
    _, truth_xyz = random_pair(T=3, J=16)
    names = list(LANDMARKS) + ["head_top"]
    xyz = np.concatenate([truth_xyz, truth_xyz[:, 3:4] + 0.1], axis=1)
    save_poses(make_poses(xyz, names=names, extra={"blob_names": np.asarray(["a", "b"])}), tmp_path / "gt.npz")
    gt = load_poses(tmp_path / "gt.npz")
    assert list(gt.extra["blob_names"]) == ["a", "b"]
    rep = evaluate(make_poses(truth_xyz), gt)
    assert rep.mpjpe_mm == pytest.approx(0, abs=1e-3) and rep.frames_evaluated == 3


@pytest.fixture
def npz_pair(tmp_path):
    rng = np.random.default_rng(7)
    truth_xyz = rng.normal(size=(12, 16, 3))
    pred_xyz = truth_xyz[2:] + rng.normal(scale=0.06, size=(10, 16, 3))
    valid = np.ones(10, bool)
    valid[3] = False  # frame 5 lost
    save_poses(make_poses(truth_xyz), tmp_path / "gt.npz")
    save_poses(make_poses(pred_xyz, frame_index=np.arange(2, 12), valid=valid), tmp_path / "pred.npz")
    keep = np.arange(2, 12)[valid]
    errs = np.linalg.norm(pred_xyz[valid].astype(np.float32).astype(np.float64)
                          - truth_xyz[keep].astype(np.float32), axis=-1)  # (9, 16), as stored
    return tmp_path / "pred.npz", tmp_path / "gt.npz", errs, keep


def test_cli_prints_and_writes_json(npz_pair, tmp_path, capsys):
    pred, gt, errs, keep = npz_pair
    out = tmp_path / "report" / "eval.json"
    assert main(["eval", str(pred), str(gt), "--pck", "0.05", "0.1", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    lines = {line.split()[0]: line for line in text.splitlines() if line.strip()}
    assert lines["MPJPE"].split()[1] == f"{1000 * errs.mean():.1f}"
    assert lines["l_knee"].split()[1] == f"{1000 * errs[:, LANDMARKS.index('l_knee')].mean():.1f}"
    assert lines["PCK@50mm"].split()[1] == f"{100 * (errs <= 0.05).mean():.1f}%"
    assert "1 lost" in text and "9 evaluated" in text
    worst = int(np.argmax(errs.mean(1)))
    assert f"(frame {keep[worst]})" in lines["max"]
    doc = json.loads(out.read_text())
    assert doc["mpjpe_mm"] == pytest.approx(1000 * errs.mean(), rel=1e-5)
    assert doc["frames_lost"] == 1 and doc["lost_frame_index"] == [5] and doc["frames_truth_only"] == 2
    assert [p["threshold_m"] for p in doc["pck"]] == [0.05, 0.1]
    assert doc["pck"][1]["fraction"] == pytest.approx((errs <= 0.1).mean())
    assert doc["per_frame_mm"] == pytest.approx(list(1000 * errs.mean(1)), rel=1e-5)
    assert doc["max_frame"] == keep[worst]


def test_cli_landmarks_option(npz_pair, capsys):
    pred, gt, errs, _ = npz_pair
    assert main(["eval", str(pred), str(gt), "--landmarks", "head", "pelvis"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines() if line.strip()}
    assert "l_knee" not in lines
    assert lines["MPJPE"].split()[1] == f"{1000 * errs[:, [3, 0]].mean():.1f}"


def test_cli_missing_or_corrupt_file(npz_pair, tmp_path, capsys):
    pred, gt, _, _ = npz_pair
    missing = tmp_path / "nope.npz"
    assert main(["eval", str(pred), str(missing)]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and len(err.strip().splitlines()) == 1
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    assert main(["eval", str(bad), str(gt)]) == 2
    assert str(bad) in capsys.readouterr().err


def test_cli_landmark_missing_from_one_file(npz_pair, tmp_path, capsys):
    pred, gt, _, _ = npz_pair
    _, truth_xyz = random_pair(T=12, J=16)
    names = list(LANDMARKS) + ["head_top"]
    save_poses(make_poses(np.concatenate([truth_xyz, truth_xyz[:, :1]], 1), names=names), tmp_path / "gt2.npz")
    assert main(["eval", str(pred), str(tmp_path / "gt2.npz"), "--landmarks", "head_top"]) == 2
    err = capsys.readouterr().err
    assert str(pred) in err and "head_top" in err
