"""The marker detection simulator: projections against OpenCV, occlusion against a closed-form loop, the detector's
statistics over many draws, and `torchtrack synth markers` on the real captures and the real rig."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from scipy import stats

from conftest import DEMO_RIG, demo_rig, shared_data
from test_docs import documented_keys
from torchtrack.cameras import load_calibration
from torchtrack.checks import InputError
from torchtrack.cli import main
from torchtrack.io.c3d import read_c3d
from torchtrack.io.markers2d import load_markers2d
from torchtrack.io.poses import load_poses
from torchtrack.markers.simulate import DetectorModel, marker_visibility, simulate_detections

def test_projections_match_opencv():
    rig = demo_rig()
    gen = torch.Generator().manual_seed(0)
    markers = torch.rand(3, 5, 3, generator=gen, dtype=torch.float64) * torch.tensor([2.0, 1.4, 1.9]) + torch.tensor(
        [-1.9, -0.7, 0.05])  # the capture area
    uv, visible = marker_visibility(markers, rig)
    for c in range(rig.num_cameras):
        R, t = rig.R_cam_world[c].numpy(), rig.t_cam_world[c].numpy()
        ref = cv2.projectPoints(markers.reshape(-1, 3).numpy(), cv2.Rodrigues(R)[0], t, rig.K[c].numpy(),
                                rig.dist[c].numpy())[0][:, 0].reshape(3, 5, 2)
        np.testing.assert_allclose(uv[:, c].numpy(), ref, atol=1e-4)  # R from float32: Rodrigues re-orthonormalises
    assert visible.float().mean() > 0.5


def test_a_sphere_hides_what_lies_behind_it():
    """Occlusion against a plain loop of the closed-form ray-sphere test (one sphere, many markers)."""
    rig = demo_rig()
    centre, radius, skin = np.array([-0.9, -0.1, 1.0]), 0.25, 0.05
    gen = np.random.default_rng(1)
    markers = centre + gen.uniform(-0.8, 0.8, size=(1, 400, 3))
    uv, visible = marker_visibility(torch.from_numpy(markers), rig, torch.from_numpy(centre)[None, None],
                                    torch.eye(3, dtype=torch.float64)[None, None],
                                    torch.full((1, 3), radius, dtype=torch.float64), skin_m=skin)
    _, in_image = marker_visibility(torch.from_numpy(markers), rig)
    eyes = rig.centers().numpy()
    for c, eye in enumerate(eyes):
        for m, p in enumerate(markers[0]):
            d = p - eye
            L = np.linalg.norm(d)
            d = d / L
            b = d @ (eye - centre)
            disc = b * b - (eye - centre) @ (eye - centre) + radius ** 2
            entry = -b - math.sqrt(disc) if disc >= 0 else math.inf
            hidden = 0 < entry < L - skin
            assert bool(visible[0, c, m]) == (bool(in_image[0, c, m]) and not hidden), (c, m)
    assert 0 < int((in_image & ~visible).sum())  # some markers are hidden


def test_detector_statistics():
    """Misses binomial, false detections Poisson with uniform pixels and labels, noise Gaussian: over many draws."""
    T, C, M, W, H = 400, 4, 30, 640, 480
    model = DetectorModel(p_miss=0.3, false_rate=0.8, sigma_px=1.5)
    gen = torch.Generator().manual_seed(5)
    truth = torch.rand(T, C, M, 2, generator=gen, dtype=torch.float64) * torch.tensor([W, H]) - 0.5
    visible = torch.rand(T, C, M, generator=gen) < 0.9
    det = simulate_detections(truth, visible, torch.tensor([[W, H]] * C), model, gen)
    found = det.true_index >= 0
    assert not bool((found & ~visible).any())
    n, k = int(visible.sum()), int(found.sum())
    assert stats.binomtest(k, n, 1 - model.p_miss).pvalue > 1e-3
    # the true candidates: the truth plus N(0, sigma^2) per axis
    t, c, m = found.nonzero().T
    err = (det.uv[t, c, m, det.true_index[found]] - truth[found]).numpy().ravel() / model.sigma_px
    assert stats.kstest(err, "norm").pvalue > 1e-3
    # the false ones: every other finite candidate
    cand = torch.isfinite(det.uv[..., 0])
    cand[t, c, m, det.true_index[found]] = False
    per_view = cand.sum((2, 3)).numpy().ravel()  # (T * C,) false detections per frame and view
    dispersion = ((per_view - per_view.mean()) ** 2).sum() / per_view.mean()  # chi-square, T*C - 1 dof
    assert stats.chi2.sf(dispersion, per_view.size - 1) > 1e-3 and stats.chi2.cdf(dispersion, per_view.size - 1) > 1e-3
    assert abs(per_view.mean() - model.false_rate) < 4 * math.sqrt(model.false_rate / per_view.size)
    fake = det.uv[cand].numpy()
    assert stats.kstest((fake[:, 0] + 0.5) / W, "uniform").pvalue > 1e-3
    assert stats.kstest((fake[:, 1] + 0.5) / H, "uniform").pvalue > 1e-3
    labels = cand.nonzero()[:, 2].numpy()
    assert stats.chisquare(np.bincount(labels, minlength=M)).pvalue > 1e-3
    # the candidates' order tells nothing: the true one is in every slot of groups with two
    pairs = found & (torch.isfinite(det.uv[..., 0]).sum(-1) == 2)
    share_first = float((det.true_index[pairs] == 0).double().mean())
    assert stats.binomtest(int((det.true_index[pairs] == 0).sum()), int(pairs.sum()), 0.5).pvalue > 1e-3, share_first


def test_the_same_seed_gives_the_same_detections():
    truth = torch.rand(20, 3, 5, 2, dtype=torch.float64) * 100
    visible = torch.ones(20, 3, 5, dtype=torch.bool)
    a, b = (simulate_detections(truth, visible, torch.tensor([[100, 100]] * 3), DetectorModel(),
                                torch.Generator().manual_seed(3)) for _ in range(2))
    assert torch.equal(a.uv.nan_to_num(-1), b.uv.nan_to_num(-1)) and torch.equal(a.true_index, b.true_index)


def test_bad_detector_settings_are_refused():
    with pytest.raises(InputError, match="p_miss"):
        DetectorModel(p_miss=1.5)
    with pytest.raises(InputError, match="sigma_px"):
        DetectorModel(sigma_px=-1.0)


def test_plug_in_gait_outputs_are_not_markers():
    c3d = read_c3d(shared_data("mocap", "btk", "c3d", "PiG_Motion-FlatFoot-Full.c3d"))
    names = {c3d.labels[i] for i in c3d.markers()}
    assert {"LASI", "RASI", "LPSI", "RPSI", "LKNE", "LANK", "C7"} <= names
    assert not names & {"LHipAngles", "LKneeMoment", "LFEO", "PELA", "CentreOfMass"}


def test_synth_markers_writes_a_capture(tmp_path, capsys):
    c3d = shared_data("mocap", "cmu", "85_02.c3d")
    rig = shared_data(*DEMO_RIG)
    out = tmp_path / "cap"
    args = ["synth", "markers", "--motion", str(c3d), "--calibration", str(rig), "--out", str(out),
            "--duration", "0.5", "--fps", "30"]
    assert main(args) == 0
    det = load_markers2d(out / "markers2d.npz")
    gt = load_poses(out / "gt.npz")
    T, C, M = det.uv.shape[:3]
    assert (T, C, M) == (15, 4, 41) and det.marker_names == gt.marker_names and "LFWT" in det.marker_names
    # the detections that are the markers lie within a few sigma of the true markers' projections
    uv, _ = load_calibration(out / "calibration.toml", warn_units=False).double().project(
        torch.from_numpy(gt.markers3d.astype(np.float64)))
    ti = det.extra["true_index"]
    t, c, m = np.nonzero(ti >= 0)
    err = np.linalg.norm(det.uv[t, c, m, ti[t, c, m]] - uv.permute(1, 0, 2, 3).numpy()[t, c, m], axis=-1)
    assert len(err) > 0.3 * T * C * M and err.max() < 6 * 2.0 * math.sqrt(2)
    with np.load(out / "markers2d.npz") as z:  # every key written is in docs/formats.md
        assert set(z.files) <= documented_keys("`markers2d.npz` (marker detections)"), z.files
    assert main(args) == 2  # an earlier capture is not replaced without --overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert main(args + ["--overwrite", "--seed", "1"]) == 0


def test_synth_markers_names_a_malformed_capture(tmp_path, capsys):
    bad = shared_data("mocap", "btk", "c3d", "Dance.c3d")
    assert main(["synth", "markers", "--motion", str(bad), "--calibration", str(shared_data(*DEMO_RIG)),
                 "--out", str(tmp_path / "x")]) == 2
    assert "Dance.c3d" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_a_scene_placed_once_gives_each_detector_and_seed_its_detections():
    """A capture placed in the rig once (:func:`marker_scene`): its projections are OpenCV's of the placed 3D markers;
    a perfect detector returns exactly the markers it shows, each at its projection; a noisy one draws the same
    detections for the same seed and others for another, and drawing leaves the scene as it was; a detector of
    another skin offset (which the occlusion was computed with) is refused."""
    from torchtrack.markers.capture import marker_scene

    rig = demo_rig()
    pig = shared_data("mocap", "btk", "c3d", "PiG_Motion-FlatFoot-Full.c3d")
    scene = marker_scene(pig, rig, 30.0, 0.3)
    X = scene.truth.markers3d.astype(np.float64)  # (T, M, 3) placed over the capture area
    T, M = X.shape[:2]
    assert scene.visible.shape == (T, rig.num_cameras, M) and 0.3 < float(scene.visible.double().mean()) < 1.0
    for c in range(rig.num_cameras):
        R, t = rig.R_cam_world[c].double().numpy(), rig.t_cam_world[c].double().numpy()
        ref = cv2.projectPoints(X.reshape(-1, 3), cv2.Rodrigues(R)[0], t, rig.K[c].double().numpy(),
                                rig.dist[c].double().numpy())[0][:, 0].reshape(T, M, 2)
        got = scene.uv[:, c].numpy()
        both = np.isfinite(got).all(-1) & np.isfinite(ref).all(-1)  # the capture's gaps, points behind a camera
        assert both.mean() > 0.5 and not scene.visible[:, c].numpy()[~both].any()
        np.testing.assert_allclose(got[both], ref[both], atol=1e-3)
    perfect = scene.detections(DetectorModel(p_miss=0.0, false_rate=0.0, sigma_px=0.0), seed=3)
    seen = scene.visible.numpy()
    assert np.array_equal(perfect.extra["true_index"] >= 0, seen)
    t, c, m = np.nonzero(seen)
    k = perfect.extra["true_index"][t, c, m]
    np.testing.assert_allclose(perfect.uv[t, c, m, k], scene.uv.numpy()[t, c, m], atol=1e-3)  # float32 pixels
    before = scene.uv.clone()
    noisy = DetectorModel(p_miss=0.2, false_rate=0.5, sigma_px=2.0)
    a, b, other = scene.detections(noisy, 0), scene.detections(noisy, 0), scene.detections(noisy, 1)
    assert np.array_equal(a.uv, b.uv, equal_nan=True) and not np.array_equal(a.uv, other.uv, equal_nan=True)
    assert torch.equal(scene.uv, before)
    with pytest.raises(InputError, match="skin_m"):
        scene.detections(DetectorModel(skin_m=0.02))
