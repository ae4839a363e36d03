"""Recovery (torchtrack.tracking.recovery): a lost track re-acquired, a lost arm searched for again, on voxelised
ground-truth bodies.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from torchtrack.blobs import BlobModel
from torchtrack.conventions import LANDMARKS
from torchtrack.occupancy.metrics import inside_ellipsoids
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import procedural_motion
from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
from torchtrack.tracking.observation import VoxelObservation

from conftest import landmarks_of as _landmarks, voxelised_observation as _observation

torch.set_grad_enabled(False)


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


def test_a_subject_back_in_another_pose_and_heading_is_reacquired(skel):
    """Tracked walking, then nobody, then back mid-squat and turned 150 degrees 0.5 m away: the re-acquisition
    (the last pose at four headings, the search where none passes the checks) lands within 50 mm of the truth
    (the pose's forward kinematics)."""
    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    walk = procedural_motion(subj, "walk", 0.3, 30, starfish_s=0.0)
    tracker = MarkerlessTracker(skel)
    for t in range(walk.shape[0]):
        assert tracker.step(_observation(subj, blobs, walk[t])).valid
    nobody = _observation(subj, blobs, walk[-1])
    nobody = VoxelObservation(nobody.points[:0], nobody.sizes[:0], nobody.weights[:0], nobody.colours[:0],
                              nobody.cameras_valid)
    assert not tracker.step(nobody).valid
    names = list(skel.dof_names)
    back = procedural_motion(subj, "squat", 1.0, 30, starfish_s=0.0)[14].clone()
    back[names.index("root_rz")] = float(walk[-1, names.index("root_rz")]) + math.radians(150)
    back[names.index("root_tx")] += 0.5
    res = tracker.step(_observation(subj, blobs, back))
    assert res.valid and res.reinitialised
    truth = subj.forward(back[None].double()).output_points[0]
    err = (res.output_points.double() - truth).norm(dim=-1).mean()
    assert float(err) < 0.05, float(err)


@pytest.mark.parametrize("trusted", [False, True])
def test_the_reacquisition_fits_in_one_batch_as_each_fitted_alone(skel, trusted):
    """MarkerlessTracker._fit_many against _track run round after round on each start in turn, as re-acquisition
    fitted its hypotheses before: a walking body's voxels, the last pose at four headings; also with the
    prediction trusted and the feet held, as the start's limb sweep fits its two states."""
    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    walk = procedural_motion(subj, "walk", 0.3, 30, starfish_s=0.0)
    tracker = MarkerlessTracker(skel)
    assert all(tracker.step(_observation(subj, blobs, a)).valid for a in walk[:4])
    obs = _observation(subj, blobs, walk[8])
    tracker.colour = None
    names = list(skel.dof_names)
    starts = tracker.angles.repeat(4, 1)
    starts[:, names.index("root_rz")] += torch.tensor([0.0, 0.5, 1.0, -0.5]).to(starts) * math.pi
    got = tracker._fit_many(obs, starts, 3, math.radians(45), predicted=trusted, hold=trusted)
    for h in range(4):
        tracker.angles = tracker.previous = starts[h]
        for _ in range(3):
            want = tracker._track(obs, learn_colour=False, max_rot=math.radians(45), predicted=trusted,
                                  hold=trusted)
            tracker.angles = tracker.previous = want.angles
        torch.testing.assert_close(got[h].angles, want.angles, rtol=1e-4, atol=1e-4)
        assert got[h].residual_m == pytest.approx(want.residual_m, rel=1e-3, abs=1e-5)
        assert got[h].explained == pytest.approx(want.explained, rel=1e-5)
        torch.testing.assert_close(got[h].confidence, want.confidence, rtol=1e-4, atol=1e-5)
    assert got[0].residual_m < min(r.residual_m for r in got[1:])  # the right heading fits best


def test_a_reacquired_body_learns_its_colours_afresh(skel):
    """A colour model learnt before a loss (here: in a light 40 % dimmer, as elsewhere in a room) is not carried
    over a re-acquisition: the re-acquired frame learns the colours again, each blob's as rendered (the synthetic
    voxels' colours), and the frames after it are tracked within 50 mm of the truth."""
    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    walk = procedural_motion(subj, "walk", 1.0, 30, starfish_s=0.0)
    tracker = MarkerlessTracker(skel)
    for t in range(10):
        assert tracker.step(_observation(subj, blobs, walk[t])).valid
    rendered = blobs.colour.float()
    wrong = 0.6 * tracker.colour.colour_mean
    assert float((wrong - rendered).abs().amax(-1).median()) > 0.1  # the corruption is one a blob would notice
    tracker.colour = dataclasses.replace(tracker.colour, colour_mean=wrong)
    nobody = _observation(subj, blobs, walk[10])
    nobody = VoxelObservation(nobody.points[:0], nobody.sizes[:0], nobody.weights[:0], nobody.colours[:0],
                              nobody.cameras_valid)
    for _ in range(3):
        assert not tracker.step(nobody).valid
    back = walk[13:20].clone()
    back[:, list(skel.dof_names).index("root_tx")] += 0.3
    for t in range(back.shape[0]):
        res = tracker.step(_observation(subj, blobs, back[t]))
        assert res.valid and res.reinitialised == (t == 0)
        if t == 0:
            known = tracker.colour.colour_known  # the blobs EM learnt a colour for on this frame
            assert int(known.sum()) >= 8, known
            assert float((tracker.colour.colour_mean - rendered)[known].abs().amax(-1).median()) < 0.03
        truth = subj.forward(back[t][None].double()).output_points[0]
        assert float((res.output_points.double() - truth).norm(dim=-1).mean()) < 0.05, t


def _lost_arm_run(skel, start_edit, lost_hand_frames, frames=8):
    """A subject 1.80 m tall standing still with the arms hanging (voxelised ground truth), tracked from its pose
    with the left arm's DOFs set by ``start_edit`` (an arm that ran off its voxels). Returns per frame the left
    wrist's error (m), whether the left hand's blob was active, and the right wrist's error (m)."""
    subj = skel.scaled_to_height(1.80)
    blobs = BlobModel.from_config(subj)
    true = subj.rest_angles()
    start = true.clone()
    for name, value in start_edit.items():
        start[skel.dof_names.index(name)] = value
    tracker = MarkerlessTracker(skel, TrackerConfig(lost_hand_frames=lost_hand_frames))
    tracker.initialize_from_pose(start, 1.80)
    obs = _observation(subj, blobs, true)
    truth = _landmarks(subj, true)
    lw, rw, hand = LANDMARKS.index("l_wrist"), LANDMARKS.index("r_wrist"), blobs.names.index("l_hand")
    left, active, right = [], [], []
    for _ in range(frames):
        r = tracker.step(obs)
        assert r.valid
        left.append(float((r.output_points[lw] - truth[lw]).norm()))
        right.append(float((r.output_points[rw] - truth[rw]).norm()))
        active.append(bool(r.blobs.active[hand]))
    return np.array(left), np.array(active), np.array(right)


@pytest.mark.parametrize("edit", [{"l_shoulder_abd": 1.5}, {"l_shoulder_flex": 2.5},
                                  {"l_shoulder_abd": 1.2, "l_elbow_flex": 2.0}])
def test_a_lost_arm_is_searched_again_from_hanging(skel, edit):
    """The left arm starts out where there are no voxels (held out sideways, raised, or bent): its hand's blob is
    empty and, de-activated, never fills again, so without the search the wrist stays 0.5-1 m off. With
    ``lost_hand_frames`` 3 the arm is searched for from hanging on the third frame the hand is off, found (it fits
    better than the frame tracked again as it was), and stays found (no velocity carries it back off); the right
    arm is not touched."""
    left, active, right = _lost_arm_run(skel, edit, 0)
    assert left.min() > 0.4 and not active.any()
    left, active, right = _lost_arm_run(skel, edit, 3)
    assert not active[:2].any() and left[:2].min() > 0.4  # the first two frames: not searched yet
    assert active[2:].all() and left[2:].max() < 0.02, left
    assert right.max() < 0.02, right


def _raised_arm_without_hand(skel):
    """A subject 1.80 m tall, the left arm raised sideways above the shoulder, whose left hand's voxels are gone
    (its ellipsoid grown by 2 cm emptied): the body, the pose, the observation and the hand's blob index."""
    subj = skel.scaled_to_height(1.80)
    blobs = BlobModel.from_config(subj)
    true = subj.rest_angles()
    true[skel.dof_names.index("l_shoulder_abd")] = 2.0
    obs = _observation(subj, blobs, true)
    k = blobs.names.index("l_hand")
    centres, R = blobs.ellipsoids(subj.forward(true[None].double()).bone_frames)
    keep = ~inside_ellipsoids(obs.points.double(), centres[0, k:k + 1], R[0, k:k + 1],
                              blobs.semi_axes[k:k + 1].double() + 0.02)
    obs = VoxelObservation(obs.points[keep], obs.sizes[keep], obs.weights[keep], obs.colours[keep],
                           obs.cameras_valid)
    return subj, true, obs, k


def _counting_searches(tracker, monkeypatch):
    """Count the tracker's extra passes of the lost-arm search (two per search)."""
    calls = []
    inner = tracker._track_again

    def counted(obs, angles):
        calls.append(1)
        return inner(obs, angles)

    monkeypatch.setattr(tracker, "_track_again", counted)
    return calls


def test_an_arm_the_voxels_do_not_show_is_kept_where_it_was(skel, monkeypatch):
    """A hand that is off because its voxels are gone, not because the arm is lost: searched for every second
    frame (``lost_hand_frames`` 2), the arm tracked again from hanging fits worse than the raised one the forearm's
    voxels show (kept, it leaves the arm off them), so the arm stays where it is, its elbow and wrist within 3 cm
    of the truth."""
    subj, true, obs, k = _raised_arm_without_hand(skel)
    tracker = MarkerlessTracker(skel, TrackerConfig(lost_hand_frames=2))
    tracker.initialize_from_pose(true, 1.80)
    calls = _counting_searches(tracker, monkeypatch)
    truth = _landmarks(subj, true)
    for t in range(6):
        r = tracker.step(obs)
        assert r.valid and not bool(r.blobs.active[k])
        for name in ("l_elbow", "l_wrist"):
            j = LANDMARKS.index(name)
            assert float((r.output_points[j] - truth[j]).norm()) < 0.03, (t, name)
    assert len(calls) == 2 * 3  # searched on the 2nd, 4th and 6th frames


def test_the_lost_hands_count_starts_again_after_a_frame_with_nobody(skel, monkeypatch):
    """Two frames with the hand off, a frame with nobody (the count starts again), the re-acquisition (not
    counted), then the third accepted frame with the hand off is the first searched (``lost_hand_frames`` 3)."""
    subj, true, obs, k = _raised_arm_without_hand(skel)
    # no race after the re-acquisition: its twin, a copy of this tracker, would call the patched search too
    tracker = MarkerlessTracker(skel, TrackerConfig(lost_hand_frames=3, start_race_s=0.0))
    tracker.initialize_from_pose(true, 1.80)
    calls = _counting_searches(tracker, monkeypatch)
    empty = VoxelObservation(obs.points[:0], obs.sizes[:0], obs.weights[:0], obs.colours[:0], obs.cameras_valid)
    for o in (obs, obs):
        tracker.step(o)
    assert tracker.hands_off == [2, 0]
    assert not tracker.step(empty).valid and tracker.hands_off == [0, 0]
    assert tracker.step(obs).reinitialised and tracker.hands_off == [0, 0]
    for _ in range(2):
        tracker.step(obs)
    assert tracker.hands_off == [2, 0] and not calls
    tracker.step(obs)
    assert len(calls) == 2 and tracker.hands_off == [0, 0]


@pytest.mark.parametrize("hold_s", [0.0, 1.0])
def test_a_walker_out_of_the_observed_volume_is_held_in_the_images(skel, hold_s):
    """A walker tracked up to the observed volume's side (x = 2.4 m) and on out of it, 5 cm a frame, the grid's
    voxels cut by the side (the voxelised body inside it), each camera's foreground its true silhouette (each
    pixel's ray met with the body's ellipsoids, clearance.body_masks): with ``image_hold_s`` each frame is tracked
    in the images, valid, within 80 mm of the truth (its forward kinematics; 4 px cells of 320x240 images, the
    far cameras 7 m away) and at ``image_hold_confidence``; without it the last, with no voxel left, is invalid."""
    from torchtrack.synth.sequence import RigConfig, make_ring_rig
    from torchtrack.tracking.clearance import body_masks
    from torchtrack.tracking.voxels import ViewSilhouettes

    tracker = MarkerlessTracker(skel, TrackerConfig(image_hold_s=hold_s))
    names = list(skel.dof_names)
    walk = procedural_motion(skel.scaled_to_height(1.75), "walk", 0.4, 30, starfish_s=0.0)
    walk[:, names.index("root_rz")] = 0.0  # facing +x, as it walks
    walk[:, names.index("root_ty")] = 0.0
    walk[:, names.index("root_tx")] = 2.2 + 0.05 * torch.arange(walk.shape[0]).to(walk)
    tracker.initialize_from_pose(walk[1], 1.75)
    tracker.previous = walk[0].clone()
    sub = tracker.subject
    rig = make_ring_rig(RigConfig(num_cameras=8, width=320, height=240, radius_m=4.5)).float()
    for t in range(2, 12):
        obs = _observation(sub.skeleton, sub.blobs, walk[t], cameras=8)
        keep = obs.points[:, 0] < 2.4
        fg = body_masks(rig, sub.skeleton, walk[t][None], blobs=sub.blobs)[0].float()
        obs = dataclasses.replace(obs, points=obs.points[keep], sizes=obs.sizes[keep], weights=obs.weights[keep],
                                  colours=obs.colours[keep], volume_m=((-2.4, -2.4, 0.0), (2.4, 2.4, 2.1)),
                                  silhouettes=ViewSilhouettes.from_evidence(2 * fg - 1, rig))
        res = tracker.step(obs)
        if hold_s > 0 and t >= 4:  # from half out of the volume
            err = float((_landmarks(sub.skeleton, res.angles) - _landmarks(sub.skeleton, walk[t])).norm(dim=-1).mean())
            assert res.valid and err < 0.08, (t, res.valid, err)  # the walker is 0.1-0.4 m out
            assert torch.all(res.confidence == tracker.config.image_hold_confidence)
    assert res.valid == (hold_s > 0) and int(keep.sum()) == 0


def test_the_frames_before_a_walker_is_reacquired_are_held_back_in_the_images(skel):
    """A lost track (a frame with nobody), then a walker coming back into the observed volume (x = 2.4 m) from
    outside it, 5 cm a frame, the grid's voxels cut by its side, each camera's foreground the true silhouette
    (clearance.body_masks): once the walker is re-acquired, the invalid frames before it where the cameras show
    the body are tracked back in their images (take_revised), valid, within 100 mm of the truth (its forward
    kinematics) and at ``image_hold_confidence``."""
    from torchtrack.synth.sequence import RigConfig, make_ring_rig
    from torchtrack.tracking.clearance import body_masks
    from torchtrack.tracking.voxels import ViewSilhouettes

    tracker = MarkerlessTracker(skel, TrackerConfig(image_hold_s=1.0, start_race_s=0.0, settle_back_s=0.0))
    names = list(skel.dof_names)
    walk = procedural_motion(skel.scaled_to_height(1.75), "walk", 0.6, 30, starfish_s=0.0)
    walk[:, names.index("root_rz")] = math.pi  # facing -x, as it walks back in
    walk[:, names.index("root_ty")] = 0.0
    walk[:, names.index("root_tx")] = 2.85 - 0.05 * torch.arange(walk.shape[0]).to(walk)
    tracker.initialize_from_pose(walk[0], 1.75)
    sub = tracker.subject
    rig = make_ring_rig(RigConfig(num_cameras=8, width=320, height=240, radius_m=4.5)).float()
    box = ((-2.4, -2.4, 0.0), (2.4, 2.4, 2.1))

    def observed(t):
        obs = _observation(sub.skeleton, sub.blobs, walk[t], cameras=8)
        keep = obs.points[:, 0] < 2.4
        fg = body_masks(rig, sub.skeleton, walk[t][None], blobs=sub.blobs)[0].float()
        return dataclasses.replace(obs, points=obs.points[keep], sizes=obs.sizes[keep], weights=obs.weights[keep],
                                   colours=obs.colours[keep], volume_m=box,
                                   silhouettes=ViewSilhouettes.from_evidence(2 * fg - 1, rig))

    nobody = observed(0)
    nobody = dataclasses.replace(nobody, points=nobody.points[:0], sizes=nobody.sizes[:0],
                                 weights=nobody.weights[:0], colours=nobody.colours[:0],
                                 silhouettes=ViewSilhouettes(torch.zeros_like(nobody.silhouettes.fg), 4, rig))
    assert not tracker.step(nobody).valid  # lost: the images do not hold a body nobody's cameras show
    for t in range(1, walk.shape[0]):
        res = tracker.step(observed(t))
        if res.valid:
            break
    assert res.reinitialised and t >= 5, t
    revised = tracker.take_revised()
    assert len(revised) >= 4 and revised[-1][0] is res, len(revised)
    for j, (r, _) in enumerate(revised[:-1]):
        truth = walk[t - len(revised) + 1 + j]
        err = float((_landmarks(sub.skeleton, r.angles) - _landmarks(sub.skeleton, truth)).norm(dim=-1).mean())
        assert r.valid and err < 0.1 and torch.all(r.confidence == 0.5), (j, r.valid, err)


def _hold_case(skel: Skeleton, where: str, height: float = 1.75) -> tuple[MarkerlessTracker, VoxelObservation]:
    """A tracker started on a voxelised body and its next frame, in a volume whose side is x = 2.4 m: the body in
    the middle; at x = 2.35 m, its voxels beyond the side removed ("cut"); or in the middle with a slab of clutter
    voxels along the side 2 m from it (a door, a ghost)."""
    from torchtrack.synth.sequence import RigConfig, make_ring_rig
    from torchtrack.tracking.voxels import ViewSilhouettes

    tracker = MarkerlessTracker(skel, TrackerConfig(image_hold_s=1.0))
    angles = skel.scaled_to_height(height).rest_angles().double()
    names = list(skel.dof_names)
    angles[names.index("root_tx")] = 2.35 if where == "cut" else 0.0
    tracker.initialize_from_pose(angles, height)
    sub = tracker.subject
    obs = _observation(sub.skeleton, sub.blobs, angles, cameras=8)
    if where == "clutter":
        y, z = torch.meshgrid(torch.arange(-0.3, 0.3, 0.03), torch.arange(0.0, 1.8, 0.03), indexing="ij")
        slab = torch.stack([torch.full_like(y, 2.385), y, z], -1).reshape(-1, 3).float()
        obs = dataclasses.replace(obs, points=torch.cat([obs.points, slab]),
                                  sizes=torch.cat([obs.sizes, obs.sizes[:1].expand(len(slab))]),
                                  weights=torch.cat([obs.weights, obs.weights[:1].expand(len(slab))]),
                                  colours=torch.cat([obs.colours, obs.colours[:1].expand(len(slab), -1, -1)]))
    keep = obs.points[:, 0] < 2.4
    assert int((~keep).sum()) > 0 if where == "cut" else int((~keep).sum()) == 0
    rig = make_ring_rig(RigConfig(num_cameras=8, width=64, height=48)).float()
    obs = dataclasses.replace(obs, points=obs.points[keep], sizes=obs.sizes[keep], weights=obs.weights[keep],
                              colours=obs.colours[keep], volume_m=((-2.4, -2.4, 0.0), (2.4, 2.4, 2.1)),
                              silhouettes=ViewSilhouettes.from_evidence(torch.ones(8, 48, 64), rig))
    return tracker, obs


@pytest.mark.parametrize("where", ["middle", "cut", "clutter"])
def test_the_images_hold_a_body_the_volume_cuts_not_one_beside_clutter_at_its_side(skel, where):
    """The image hold's trigger on voxelised bodies in a volume whose side is x = 2.4 m: a body in the middle, no;
    a body at x = 2.35 m whose voxels the side cuts (those beyond it removed), yes; the body in the middle with a
    slab of clutter voxels along the side 2 m from it (a door, a ghost), no."""
    tracker, obs = _hold_case(skel, where)
    assert (tracker._hold_prediction(obs) is not None) == (where == "cut")


def test_the_image_hold_tests_many_trackers_at_once_as_each_alone(skel):
    """``hold_tests`` of four trackers at once (bodies of 1.6-1.9 m; voxel sets of different sizes, padded; one frame
    with no voxels at all, whose body is out of the volume): the predictions and answers each tracker's own test
    gives, and the right answers (the cut body and the body out of the volume held, the others not)."""
    from torchtrack.tracking.recovery import hold_tests
    from torchtrack.tracking.step import SubjectStack

    cases = [_hold_case(skel, w, h) for w, h in (("middle", 1.6), ("cut", 1.75), ("clutter", 1.9), ("cut", 1.7))]
    tracker, obs = cases[3]  # walked out of the volume: no voxels left
    tracker.angles[list(skel.dof_names).index("root_tx")] = 2.9
    tracker.previous = tracker.angles.clone()
    cases[3] = tracker, dataclasses.replace(obs, points=obs.points[:0], sizes=obs.sizes[:0],
                                            weights=obs.weights[:0], colours=obs.colours[:0])
    trackers, observations = zip(*cases)
    predicted, hold = hold_tests(trackers, observations, SubjectStack([t.subject for t in trackers]))
    assert hold.tolist() == [False, True, False, True]
    for k, (tracker, obs) in enumerate(cases):
        alone = tracker._hold_prediction(obs)
        assert (alone is not None) == bool(hold[k]), k
        if alone is not None:
            torch.testing.assert_close(predicted[k], alone, rtol=0, atol=1e-12)


def _checked_run(skel, turned: bool, unchecked: int, narrow: int = 0):
    """A walker (its circle in the middle of a 4.8 m volume) tracked from a pose given on its first frame (its true
    pose, or turned round: the heading a re-acquisition at the volume's edge guessed wrong) with ``unchecked``
    frames of the check left, as a re-acquisition leaves them (``recheck_s``); on the first ``narrow`` frames the
    observed volume's side x passes through the walker's root (its voxels all kept, but half the body out of the
    volume: the search does not look there, and the plain step silences the blobs out of it); the start race and
    the track back off. Returns the results, their errors (mean landmark distance to the truth, the poses' forward
    kinematics, m), the frames the search ran on and the tracker."""
    from torchtrack.tracking.poses import turned_round

    subj = skel.scaled_to_height(1.75)
    walk = procedural_motion(subj, "walk", 0.7, 30, starfish_s=0.0)
    x = walk[:, list(skel.dof_names).index("root_tx")]
    tracker = MarkerlessTracker(skel, TrackerConfig(start_race_s=0.0, settle_back_s=0.0))
    tracker.set_frame_rate(30.0)
    tracker.initialize_from_pose(turned_round(skel, walk[0]) if turned else walk[0], 1.75)
    tracker.unchecked = unchecked
    sub = tracker.subject
    searched = []
    search = tracker._searched
    tracker._searched = lambda obs: searched.append(len(results)) or search(obs)
    results = []
    for t in range(1, walk.shape[0]):
        side = float(x[t]) if t <= narrow else 2.4
        obs = dataclasses.replace(_observation(sub.skeleton, sub.blobs, walk[t], cameras=8),
                                  volume_m=((-2.4, -2.4, 0.0), (side, 2.4, 2.1)))
        results.append(tracker.step(obs))
    errors = [float((_landmarks(sub.skeleton, r.angles) - _landmarks(sub.skeleton, walk[t + 1])).norm(dim=-1).mean())
              for t, r in enumerate(results)]
    return results, errors, searched, tracker


def test_a_reacquisition_turned_round_is_mended_by_its_check(skel):
    """A track that faces the wrong way with the check pending (as a re-acquisition leaves it; the pose given, the
    check's frames set): the check runs the search on the first frame and re-acquires from its answer, and from
    there the track is within 50 mm of the truth. With no check left, the same track stays turned round (over
    100 mm on every frame)."""
    results, errors, searched, tracker = _checked_run(skel, turned=True, unchecked=30)
    assert results[0].reinitialised and searched == [0] and tracker.unchecked == 0, searched
    assert all(r.valid for r in results) and max(errors) < 0.05, errors
    _, unmended, searched, _ = _checked_run(skel, turned=True, unchecked=0)
    assert searched == [] and min(unmended) > 0.1, unmended


def test_a_reacquisition_is_checked_once_the_body_is_inside_the_volume_and_a_right_one_stands(skel):
    """The check of a track that faces the right way: no search while the volume's side passes through the body,
    one on the first frame it does not, and the track stands: the same to the bit as with no check. With the
    check's frames spent while the body was out, no search at all."""
    results, errors, searched, tracker = _checked_run(skel, turned=False, unchecked=30, narrow=5)
    assert searched == [5] and tracker.unchecked == 0, searched
    plain, _, none, _ = _checked_run(skel, turned=False, unchecked=0, narrow=5)
    assert none == [] and all(torch.equal(a.angles, b.angles) for a, b in zip(results, plain))
    assert max(errors[5:]) < 0.05, errors
    results, errors, searched, tracker = _checked_run(skel, turned=False, unchecked=4, narrow=5)
    assert searched == [] and tracker.unchecked == 0 and max(errors[5:]) < 0.05, searched


@pytest.mark.parametrize("recheck_s", [0.0, 2.0])
def test_a_reacquisition_leaves_its_check_as_recheck_s_says(skel, recheck_s):
    """A walker lost (a frame with nobody) and back: the re-acquisition leaves ``recheck_s`` of frames to check it
    in (none with 0, the check off); a negative setting is refused, naming it."""
    from torchtrack.checks import InputError

    with pytest.raises(InputError, match="recheck_s"):
        TrackerConfig(recheck_s=-1.0)
    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    walk = procedural_motion(subj, "walk", 0.3, 30, starfish_s=0.0)
    tracker = MarkerlessTracker(skel, TrackerConfig(recheck_s=recheck_s, start_race_s=0.0))
    tracker.set_frame_rate(30.0)
    tracker.initialize_from_pose(walk[0], 1.75)
    nobody = _observation(subj, blobs, walk[1])
    nobody = VoxelObservation(nobody.points[:0], nobody.sizes[:0], nobody.weights[:0], nobody.colours[:0],
                              nobody.cameras_valid)
    assert not tracker.step(nobody).valid and tracker.unchecked == 0
    assert tracker.step(_observation(subj, blobs, walk[2])).reinitialised
    assert tracker.unchecked == round(recheck_s * 30)
