"""The finished track's low-pass filter (torchtrack/tracking/smoothing.py), against closed forms, scipy's filter
run on each run by hand and the ground truth of a noisy synthetic track."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.signal import butter, sosfiltfilt

from torchtrack.checks import InputError
from torchtrack.io.poses import Poses
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import procedural_motion
from torchtrack.tracking.smoothing import MIN_RUN_FRAMES, SmoothingConfig, smooth_track, valid_runs


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


def _track(skel: Skeleton, angles: np.ndarray, fps: float, valid=None, reinit=None) -> Poses:
    """A track of ``skel`` at ``angles (T, D)``, its points their forward kinematics (NaN where not valid)."""
    T = angles.shape[0]
    valid = np.ones(T, bool) if valid is None else np.asarray(valid, bool)
    angles = np.where(valid[:, None], angles, np.nan).astype(np.float32)
    j3d = np.full((T, len(skel.output_names), 3), np.nan, np.float32)
    j3d[valid] = skel.forward(torch.from_numpy(angles[valid])).output_points.numpy()
    extra = {} if reinit is None else {"reinitialised": np.asarray(reinit, bool)}
    return Poses(fps=fps, frame_index=np.arange(T), joint_names=list(skel.output_names), joints3d=j3d,
                 dof_names=list(skel.dof_names), angles=angles, valid=valid,
                 confidence=np.ones((T, len(skel.output_names)), np.float32), extra=extra)


def test_config_defaults_are_the_shipped_config_and_bad_settings_are_named():
    from torchtrack.tracking.pipeline import load_config

    cfg = load_config("markerless.yaml")
    assert SmoothingConfig.from_dict(cfg["smoothing"], cfg["source"]) == SmoothingConfig()
    assert SmoothingConfig().cutoff_hz == 6.0 and SmoothingConfig.from_dict(None).order == 4
    for doc, match in (({"cutoff_hz": -1}, "cutoff_hz must be a number >= 0"),
                       ({"cutoff_hz": "6"}, "cutoff_hz must be a number"),
                       ({"cutoff_hz": float("nan")}, "cutoff_hz must be a number"),
                       ({"order": 0}, r"order must be a whole number in \[1, 8\]"),
                       ({"order": True}, "order must be a whole number"),
                       ({"cutof_hz": 6}, r"x\.yaml: unknown smoothing settings \['cutof_hz'\]")):
        with pytest.raises(InputError, match=match):
            SmoothingConfig.from_dict(doc, "x.yaml")


def test_valid_runs_split_at_invalid_frames_and_breaks():
    valid = [0, 1, 1, 1, 0, 0, 1, 1, 1, 1, 1, 0, 1]
    assert valid_runs(np.array(valid, bool)) == [(1, 4), (6, 11), (12, 13)]
    breaks = np.zeros(13, bool)
    breaks[[2, 8, 9]] = True  # a break on a run's first frame changes nothing; 8 and 9 cut it twice
    assert valid_runs(np.array(valid, bool), breaks) == [(1, 2), (2, 4), (6, 8), (8, 9), (9, 11), (12, 13)]
    assert valid_runs(np.zeros(3, bool)) == [] and valid_runs(np.ones(3, bool)) == [(0, 3)]
    assert valid_runs(np.zeros(0, bool)) == []
    rng = np.random.default_rng(3)
    for _ in range(50):  # against a plain loop over the frames
        valid, breaks = rng.random(40) < 0.8, rng.random(40) < 0.1
        runs, start = [], None
        for t in range(40):
            if start is not None and (not valid[t] or breaks[t]):
                runs.append((start, t))
                start = None
            if valid[t] and start is None:
                start = t
        runs += [] if start is None else [(start, 40)]
        assert valid_runs(valid, breaks) == runs


@pytest.mark.parametrize("freq_hz", [2.0, 4.5, 9.0])
def test_a_sinusoid_comes_out_scaled_by_the_filters_closed_form_gain(skel, freq_hz):
    """A joint angle oscillating at f around its mid-range, 60 fps, 6 Hz: away from the ends, the forward-backward
    4th-order Butterworth scales it by |H|^2 = 1 / (1 + (tan(pi f / fs) / tan(pi fc / fs))^8) (the bilinear
    transform's squared magnitude, applied twice) without shifting it."""
    fps, fc, T = 60.0, 6.0, 240
    t = np.arange(T) / fps
    angles = np.repeat(skel.rest_angles().numpy()[None].astype(np.float64), T, 0)
    k = skel.dof_names.index("l_elbow_flex")
    mid = 0.5 * float(skel.lower[k] + skel.upper[k])
    angles[:, k] = mid + 0.3 * np.sin(2 * np.pi * freq_hz * t)
    out = smooth_track(_track(skel, angles, fps), skel, SmoothingConfig(fc, 4))
    gain = 1.0 / (1.0 + (math.tan(math.pi * freq_hz / fps) / math.tan(math.pi * fc / fps)) ** 8)
    inner = slice(60, 180)
    expected = mid + gain * 0.3 * np.sin(2 * np.pi * freq_hz * t[inner])
    assert np.abs(out.angles[inner, k] - expected).max() < 2e-3 + 0.01 * 0.3 * gain, (freq_hz, gain)
    assert float(out.extra["smoothing_cutoff_hz"]) == fc


def test_points_are_the_skeletons_pose_runs_are_filtered_apart_and_short_runs_and_invalid_frames_kept(skel):
    """Each run (split by an invalid frame and a re-initialisation) equals scipy's filter run on it alone, the
    root's angles unwrapped; a run under MIN_RUN_FRAMES and the invalid frames are left; the points are the
    skeleton's forward kinematics of the smoothed angles."""
    fps = 30.0
    clean = procedural_motion(skel, "kick", 2.0, fps, starfish_s=0.2).double().numpy()  # (T, D)
    T = clean.shape[0]
    noisy = clean + 0.02 * np.random.default_rng(0).standard_normal(clean.shape) * (np.arange(clean.shape[1]) >= 3)
    valid = np.ones(T, bool)
    valid[[20, 21]] = False
    valid[30 + MIN_RUN_FRAMES - 1] = False  # frames 30 .. 36 after the re-initialisation at 30: a short run
    reinit = np.zeros(T, bool)
    reinit[30] = True
    track = _track(skel, noisy, fps, valid, reinit)
    out = smooth_track(track, skel, SmoothingConfig(6.0, 4))
    sos = butter(4, 6.0 / (fps / 2), output="sos")
    rot = [skel.dof_names.index(n) for n in ("root_rz", "root_ry", "root_rx")]
    lo, hi = skel.lower.double().numpy(), skel.upper.double().numpy()
    for a, b in ((0, 20), (22, 30), (30 + MIN_RUN_FRAMES, T)):
        run = track.angles[a:b].astype(np.float64)
        run[:, rot] = np.unwrap(run[:, rot], axis=0)
        ref = sosfiltfilt(sos, run, axis=0, padlen=min(15, b - a - 1))
        ref[:, 6:] = np.clip(ref[:, 6:], lo[6:], hi[6:])
        np.testing.assert_allclose(out.angles[a:b], ref, atol=2e-6)
    short = slice(30, 30 + MIN_RUN_FRAMES - 1)
    np.testing.assert_array_equal(out.angles[short], track.angles[short])
    np.testing.assert_array_equal(out.joints3d[short], track.joints3d[short])
    assert np.isnan(out.angles[~valid]).all() and np.isnan(out.joints3d[~valid]).all()
    np.testing.assert_array_equal(out.valid, valid)
    fk = skel.forward(torch.from_numpy(out.angles[valid])).output_points.numpy()
    np.testing.assert_allclose(out.joints3d[valid], fk, atol=1e-6)
    inside = (out.angles[valid][:, 6:] >= lo[6:] - 1e-6) & (out.angles[valid][:, 6:] <= hi[6:] + 1e-6)
    assert inside.all()


def test_noise_on_a_true_track_is_removed(skel):
    """A procedural walk's true angles with 0.03 rad of frame noise per joint (2 cm on the root): the smoothed
    track's landmarks are closer to the truth's (the ground truth is the reference). White noise keeps the share of
    its power under the cut-off, 6 of the 15 Hz band at 30 fps: about sqrt(0.4) = 0.63 of its size."""
    fps = 30.0
    clean = procedural_motion(skel, "walk", 3.0, fps, starfish_s=0.5).double().numpy()
    rng = np.random.default_rng(1)
    noise = rng.standard_normal(clean.shape) * np.r_[[0.02] * 3, [0.03] * (clean.shape[1] - 3)]
    truth = _track(skel, clean, fps).landmarks()
    noisy = _track(skel, np.clip(clean + noise, skel.lower.numpy(), skel.upper.numpy()), fps)
    smoothed = smooth_track(noisy, skel, SmoothingConfig())
    before = np.linalg.norm(noisy.landmarks() - truth, axis=-1).mean()
    after = np.linalg.norm(smoothed.landmarks() - truth, axis=-1).mean()
    assert after < 0.7 * before, (before, after)


def test_a_turn_through_180_degrees_has_no_jump(skel):
    """The heading turning at a constant rate through +-180 deg, kept continuous (as the tracker writes it) or
    wrapped to (-pi, pi] (another tool's track): a line, which the filter keeps as it is, on the branch of the first
    frame and without a 2 pi step (filtering the wrapped values would smear one)."""
    fps, T = 30.0, 90
    angles = np.repeat(skel.rest_angles().numpy()[None].astype(np.float64), T, 0)
    k = skel.dof_names.index("root_rz")
    heading = 2.0 + 0.05 * np.arange(T)  # 2 .. 6.45 rad
    for given in (heading, (heading + np.pi) % (2 * np.pi) - np.pi):
        angles[:, k] = given
        out = smooth_track(_track(skel, angles, fps), skel, SmoothingConfig())
        np.testing.assert_allclose(out.angles[:, k], heading, atol=1e-4)
        assert out.angles.dtype == np.float32 and out.joints3d.dtype == np.float32


def test_only_short_runs_nan_frames_and_bad_frame_rates(skel):
    """Nothing filtered is recorded as 0 Hz; a valid frame with NaN angles splits its run instead of spreading
    over it; a frame rate that is not a positive number is named."""
    fps = 30.0
    angles = procedural_motion(skel, "walk", 1.0, fps, starfish_s=0.2).double().numpy()  # (36, D)
    T = angles.shape[0]
    valid = np.ones(T, bool)
    valid[::MIN_RUN_FRAMES - 1] = False  # runs of MIN_RUN_FRAMES - 2 frames only
    track = _track(skel, angles, fps, valid)
    out = smooth_track(track, skel, SmoothingConfig())
    assert float(out.extra["smoothing_cutoff_hz"]) == 0.0
    np.testing.assert_array_equal(out.angles, track.angles)
    none = _track(skel, angles, fps, np.zeros(T, bool))
    assert float(smooth_track(none, skel, SmoothingConfig()).extra["smoothing_cutoff_hz"]) == 0.0
    track = _track(skel, angles, fps)
    track.angles[15, 10] = np.nan  # a valid frame the filter cannot take: runs 0-14 and 16-35
    out = smooth_track(track, skel, SmoothingConfig())
    assert float(out.extra["smoothing_cutoff_hz"]) == 6.0 and np.isfinite(out.angles[:15]).all()
    assert np.isfinite(out.angles[16:]).all() and np.isnan(out.angles[15, 10])
    for fps_bad in (float("nan"), 0.0):
        bad = Poses(**{**track.__dict__, "fps": fps_bad})
        with pytest.raises(InputError, match="frame rate must be a positive number"):
            smooth_track(bad, skel, SmoothingConfig())


def test_off_and_over_nyquist_leave_the_track_and_a_foreign_skeleton_is_named(skel):
    fps = 20.0
    angles = procedural_motion(skel, "walk", 1.0, fps, starfish_s=0.2).double().numpy()
    track = _track(skel, angles + 0.01, fps)
    for cfg in (SmoothingConfig(0.0), SmoothingConfig(10.0), SmoothingConfig(12.0)):  # Nyquist: 10 Hz
        out = smooth_track(track, skel, cfg)
        np.testing.assert_array_equal(out.angles, track.angles)
        np.testing.assert_array_equal(out.joints3d, track.joints3d)
        assert float(out.extra["smoothing_cutoff_hz"]) == 0.0
    other = Poses(**{**track.__dict__, "dof_names": track.dof_names[:-1], "angles": track.angles[:, :-1]})
    with pytest.raises(InputError, match="degrees of freedom"):
        smooth_track(other, skel, SmoothingConfig())
