"""Bone lengths fitted while tracking (torchtrack.tracking.bone_fit) against the true proportions of voxelised
bodies.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchtrack.blobs import BlobModel
from torchtrack.checks import InputError, ShapeError
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import procedural_motion
from torchtrack.tracking.goals import GoalModel
from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
from torchtrack.tracking.observation import VoxelObservation

from conftest import landmarks_of as _landmarks, voxelised_observation as _observation

torch.set_grad_enabled(False)


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


@pytest.mark.parametrize("bone_fit", ["blobs", "shape"])
def test_fitted_bone_lengths_move_towards_a_differently_proportioned_body(skel, bone_fit):
    """fit_bone_lengths at the starfish frame, on the voxels of a body of other proportions than the template's:
    the torso's and legs' lengths and the neck's height move towards the body's, and the track is better than
    with one scale for the body; with either bone fit (the blobs EM fits, or the body's ellipsoids fitted to the
    voxels)."""
    subj, blobs, T = _proportioned_body(skel)
    errs, bones = {}, {}
    for fit in (False, True):
        # the starfish start: its scale from the voxels' height is the single scale the fit is measured against
        tracker = MarkerlessTracker(skel, TrackerConfig(fit_bone_lengths=fit, bone_fit=bone_fit, start="starfish"))
        errs[fit] = _track_body(tracker, subj, blobs, T).mean()
        bones[fit] = dict(zip(subj.bone_names, tracker.subject.skeleton.bone_lengths.tolist()))
        fitted = tracker.subject.skeleton
        bones[fit]["neck above shoulders"] = fitted.proportions()["neck_above_shoulders"]
        bones[fit]["shoulder height"] = fitted.joint_origin("l_shoulder_flex")[2]
    true = dict(zip(subj.bone_names, subj.bone_lengths.tolist()))
    true["neck above shoulders"] = subj.proportions()["neck_above_shoulders"]
    true["shoulder height"] = subj.joint_origin("l_shoulder_flex")[2]
    print({k: (round(true[k], 3), round(bones[False][k], 3), round(bones[True][k], 3)) for k in
           ("torso", "l_thigh", "r_shank", "neck above shoulders", "shoulder height")}, errs)
    # each at least a fifth of the way from one scale to the truth; the shoulders' height (the torso's blobs'
    # span less the neck's drop, the least determined) a tenth: the fit stops at its first round that fits the
    # voxels worse, here the fifth (torso 0.45 -> 0.41 of a true 0.33, shoulders 0.380 -> 0.372 of 0.332)
    for bone, part in (("torso", 0.2), ("l_thigh", 0.2), ("r_shank", 0.2), ("neck above shoulders", 0.2),
                       ("shoulder height", 0.1)):
        assert abs(bones[True][bone] - true[bone]) < (1 - part) * abs(bones[False][bone] - true[bone]), (bone, bones)
    # the track's mean error: 0.58 of the single scale's with the shanks' blobs at half the bone, 0.60 at 0.45
    assert errs[True] < 0.65 * errs[False], errs


def _proportioned_body(skel):
    """A 1.80 m body whose proportions one height scale cannot represent (torso 0.85x, legs 1.1x, the neck 6 cm
    lower on the torso, as the retargeted CMU bodies), its blobs and 6 frames of a walk from the starfish."""
    subj = skel.scaled_to_height(1.80)
    length = dict(zip(subj.bone_names, subj.bone_lengths.tolist()))
    legs = ("l_thigh", "r_thigh", "l_shank", "r_shank")
    subj = subj.with_bone_lengths({"torso": 0.85 * length["torso"], **{b: 1.1 * length[b] for b in legs}})
    x, y, z = subj.joint_origin("neck_flex")
    subj = subj.with_joint_origins({"neck_flex": (x, y, z - 0.06)})  # the shoulders stay
    return subj, BlobModel.from_config(subj), procedural_motion(subj, "walk", 6 / 30, 30, starfish_s=0.1)


def _track_body(tracker, subj, blobs, T):
    """Track the voxels of ``subj`` in the poses ``T``; every frame must be valid. Mean landmark error per frame."""
    errs = []
    for t in range(T.shape[0]):
        r = tracker.step(_observation(subj, blobs, T[t]))
        assert r.valid
        errs.append(float((r.output_points[:16] - _landmarks(subj, T[t])).norm(dim=-1).mean()))
    return np.array(errs)


def test_refit_bone_lengths_on_several_frames_moves_the_body_towards_the_truth(skel):
    """refit_bone_lengths: the template scaled to the subject's height, refitted at once on three frames of the
    proportioned body's walk (at their true poses, the voxels of the second and third shifted by a few cm as a
    track's root would be off): the torso, the legs and the neck's height move at least half way to the truth.
    Bad input: no subject yet, angles of the wrong shape, no frames."""
    subj, blobs, T = _proportioned_body(skel)
    tracker = MarkerlessTracker(skel)
    with pytest.raises(InputError, match="no subject"):
        tracker.refit_bone_lengths([_observation(subj, blobs, T[0])], T[:1])
    tracker.initialize_from_pose(T[0], 1.80)
    start = tracker.subject.skeleton
    frames = [0, 3, 5]
    shifts = [(0.0, 0.0, 0.0), (0.02, -0.01, 0.0), (-0.01, 0.0, 0.02)]
    observations = [_observation(subj, blobs, T[t], shift=s) for t, s in zip(frames, shifts)]
    fitted, change = tracker.refit_bone_lengths(observations, T[frames])
    assert change > 0.05
    true_p, start_p, got_p = subj.proportions(), start.proportions(), fitted.proportions()
    for part in ("torso", "l_thigh", "l_shank", "neck_above_shoulders"):
        assert abs(got_p[part] - true_p[part]) < 0.5 * abs(start_p[part] - true_p[part]), (part, got_p, true_p)
    assert tracker.subject.skeleton is start  # the subject is the caller's to change
    with pytest.raises(ShapeError, match="angles"):
        tracker.refit_bone_lengths(observations, T[:2])
    with pytest.raises(InputError, match="no frames"):
        tracker.refit_bone_lengths([], T[:0])


def test_initial_pose_with_the_subjects_skeleton_tracks_its_proportions(skel):
    """A start from a given skeleton (as the background refinement's later passes reuse the first pass's fitted
    one) keeps that body: on a body one height scale cannot represent, its track is closer to the truth than a
    start from the generic body scaled to the same height."""
    subj, blobs, T = _proportioned_body(skel)
    own = MarkerlessTracker(skel)
    own.initialize_from_pose(T[0], skeleton=subj)
    assert own.subject.skeleton is subj
    generic = MarkerlessTracker(skel)
    generic.initialize_from_pose(T[0], 1.80)
    err_own, err_generic = _track_body(own, subj, blobs, T), _track_body(generic, subj, blobs, T)
    assert err_own.mean() < 0.01, err_own
    assert err_generic.mean() > 2 * err_own.mean(), (err_generic, err_own)


def test_the_bone_fit_pulls_what_the_voxels_do_not_tell_back_to_its_start(skel):
    """The bone fit's ridge is towards the body the fit started from, not each round's: with voxels of the legs
    only, a round that starts from a body with a longer torso (the neck's height on it) and a shorter head gives
    them back the start's lengths (towards the round's own body they would stay, and rounds could walk along what
    the voxels hardly tell apart), while the legs follow their voxels."""
    from torchtrack.tracking.markerless import BONE_FIT_VOXEL_M, FrameResult

    subj = skel.scaled_to_height(1.80)
    length = dict(zip(subj.bone_names, subj.bone_lengths.tolist()))
    subj = subj.with_bone_lengths({b: 1.1 * length[b] for b in ("l_thigh", "r_thigh", "l_shank", "r_shank")})
    a = subj.starfish_angles()
    hip_z = float(subj.forward(a[None]).output_points[0, list(subj.output_names).index("l_hip"), 2])
    obs = _observation(subj, BlobModel.from_config(subj), a, voxel=0.02)
    legs = obs.points[:, 2] < hip_z - 0.1
    obs = VoxelObservation(obs.points[legs], obs.sizes[legs], obs.weights[legs], obs.colours[legs],
                           obs.cameras_valid)
    tracker = MarkerlessTracker(skel)
    tracker._setup(1.80, torch.device("cpu"))
    start = tracker.subject.skeleton
    start_len = dict(zip(start.bone_names, start.bone_lengths.tolist()))
    tracker._use(start.with_bone_lengths({"torso": 1.2 * start_len["torso"], "head": 0.8 * start_len["head"]}))
    res = FrameResult(angles=a, output_points=None, confidence=None, valid=True, residual_m=0.0, explained=1.0,
                      reinitialised=False, blobs=None, bone_frames=None)
    fitted, _ = tracker._fit_bone_lengths(obs.split(BONE_FIT_VOXEL_M), res, start)
    got = dict(zip(fitted.bone_names, fitted.bone_lengths.tolist()))
    assert got["torso"] == pytest.approx(start_len["torso"], rel=0.02), (got["torso"], start_len["torso"])
    assert got["head"] == pytest.approx(start_len["head"], rel=0.02), (got["head"], start_len["head"])
    assert abs(got["l_thigh"] - 1.1 * length["l_thigh"]) < 0.5 * abs(start_len["l_thigh"] - 1.1 * length["l_thigh"])
    # towards the round's own body, the torso would keep most of its 20 %
    own, _ = tracker._fit_bone_lengths(obs.split(BONE_FIT_VOXEL_M), res, tracker.subject.skeleton)
    assert dict(zip(own.bone_names, own.bone_lengths.tolist()))["torso"] > 1.15 * start_len["torso"]


def test_a_bone_fit_round_that_worsens_the_fit_is_undone(skel, monkeypatch):
    """Feedback between the bone fit and the pose can run away (the hull's torso grew round after round on
    CMU 131_01): the first round whose body fits the voxels worse than the one before is undone and ends the fit.
    Here every round after the first returns a body with a longer torso and shorter legs, as in that run-away."""
    real = MarkerlessTracker._fit_bone_lengths
    calls = []

    def running_away(self, obs, res, start):
        skel_fit, change = real(self, obs, res, start)
        calls.append(skel_fit)
        if len(calls) == 1:
            return skel_fit, change
        length = dict(zip(skel_fit.bone_names, calls[0].bone_lengths.tolist()))
        k = 1 + 0.15 * (len(calls) - 1)
        legs = ("l_thigh", "r_thigh", "l_shank", "r_shank")
        return calls[0].with_bone_lengths({"torso": k * length["torso"], **{b: length[b] / k for b in legs}}), 0.1

    monkeypatch.setattr(MarkerlessTracker, "_fit_bone_lengths", running_away)
    subj, blobs, T = _proportioned_body(skel)
    tracker = MarkerlessTracker(skel, TrackerConfig(fit_bone_lengths=True, start="starfish"))  # its first fit
    errs = _track_body(tracker, subj, blobs, T)
    assert len(calls) == 2  # the first (real) round lowered the cost, the run-away one raised it and ended the fit
    np.testing.assert_allclose(tracker.subject.skeleton.bone_lengths.numpy(), calls[0].bone_lengths.numpy(),
                               rtol=1e-6)
    assert np.mean(errs) < 0.03, errs


@pytest.mark.parametrize("girth", [0.9, 1.2])
def test_the_start_measures_the_subjects_girth_in_the_cameras_foreground(skel, girth):
    """A body slimmer or stouter than the template (every blob's cross semi-axes times ``girth``, as the synthetic
    subjects are drawn), seen by 4 cameras: at its true pose on the template scaled to its height, the girth fit
    picks its girth from the cameras' foreground; started by the search on its carved hull, the tracker's subject
    ends with that girth, its blobs' cross semi-axes the template's times it."""
    from conftest import carved_observation

    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    blobs.semi_axes[:, 1:] *= girth
    angles = procedural_motion(subj, "walk", 0.5, 30, starfish_s=0.0)[10].float()
    obs = carved_observation(subj, blobs, angles, 4, silhouettes=True)
    tracker = MarkerlessTracker(skel, TrackerConfig())
    tracker.initialize_from_pose(angles, height_m=subj.height())
    assert tracker._fit_girth(obs, angles) == pytest.approx(girth)
    tracker = MarkerlessTracker(skel, TrackerConfig())
    assert tracker.step(obs).valid
    assert tracker.girth == pytest.approx(girth, abs=0.051)
    template = BlobModel.from_config(tracker.subject.skeleton)
    torch.testing.assert_close(tracker.subject.blobs.semi_axes[:, 1:], template.semi_axes[:, 1:] * tracker.girth)
    # the goals keep the template's main axes (a stout hand's width must not take the place of its axis)
    goals = GoalModel(tracker.subject.skeleton, template)
    for name in ("elongated", "principal"):
        assert torch.equal(getattr(tracker.subject.goals, name), getattr(goals, name)), name
    tracker.reset()
    assert tracker.girth == 1.0


def test_the_girth_is_not_fitted_from_7_cameras(skel):
    """From 7 cameras (beyond ``ghost_max_cameras``) the start keeps the template's girth, a stout body or not."""
    from conftest import carved_observation

    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    blobs.semi_axes[:, 1:] *= 1.2
    angles = procedural_motion(subj, "walk", 0.5, 30, starfish_s=0.0)[10].float()
    tracker = MarkerlessTracker(skel, TrackerConfig())
    assert tracker.step(carved_observation(subj, blobs, angles, 8, silhouettes=True)).valid
    assert tracker.girth == 1.0
