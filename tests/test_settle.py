"""Tracking back from a settled track (torchtrack.tracking.settle): the frames after a re-acquisition that started
from a wrong guess are tracked again backwards from where the track has found the body, on voxelised ground-truth
bodies.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchtrack.blobs import BlobModel
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import procedural_motion
from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
from torchtrack.tracking.observation import VoxelObservation

from conftest import apply_revised, landmarks_of as _landmarks, search_turned_round
from conftest import voxelised_observation as _observation

torch.set_grad_enabled(False)

#: The right arm's DOFs the wrong guess moves (radians added): raised forward and out, the elbow bent.
WRONG_ARM = {"r_shoulder_flex": 0.9, "r_shoulder_abd": 0.5, "r_elbow_flex": 0.8}


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


def _track_reacquired(skel: Skeleton, monkeypatch, settle_s: float, frames: int = 42,
                      finish: bool = False) -> tuple[list, np.ndarray, list[int]]:
    """A walker tracked for 1 s, lost for three frames, back with the re-acquired pose's right arm raised wrongly
    (just before the re-acquired frame learns its colours); the next ``frames`` (at 30 frames/s) tracked with
    ``settle_back_s = settle_s`` (the start race and the re-acquisition's check off, to leave the settle-back
    alone), then, with ``finish``, the
    sequence ended (:meth:`MarkerlessTracker.finish`). Returns the results after revisions, each frame's MPJPE (m)
    against the walk's forward kinematics, and the lengths of the revisions."""
    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    walk = procedural_motion(subj, "walk", 2.5, 30, starfish_s=0.0)
    tracker = MarkerlessTracker(skel, TrackerConfig(start_race_s=0.0, settle_back_s=settle_s, recheck_s=0.0))
    tracker.set_frame_rate(30.0)
    for t in range(30):
        assert tracker.step(_observation(subj, blobs, walk[t])).valid
        tracker.take_revised()
    assert not tracker.settling  # the start's frames were tracked back (or not kept) after settle_s
    empty = _observation(subj, blobs, walk[30])
    empty = VoxelObservation(empty.points[:0], empty.sizes[:0], empty.weights[:0], empty.colours[:0],
                             empty.cameras_valid)
    for _ in range(3):
        assert not tracker.step(empty).valid
    names = list(skel.dof_names)
    armed = [True]
    learn = MarkerlessTracker._learn_colour

    def wrong_arm(self, obs):
        if armed[0]:
            armed[0] = False
            self.angles = self.angles.clone()
            for name, delta in WRONG_ARM.items():
                self.angles[names.index(name)] += delta
            self.previous = self.angles
        return learn(self, obs)

    monkeypatch.setattr(MarkerlessTracker, "_learn_colour", wrong_arm)
    out, lengths = [], []
    for t in range(33, 33 + frames + 1):
        if t < 33 + frames:
            out.append(tracker.step(_observation(subj, blobs, walk[t])))
        elif finish:
            tracker.finish()
        late = tracker.take_revised()
        for j, (res, version) in enumerate(late):
            out[len(out) - len(late) + j] = res
            assert version == tracker.body_version
        if late:
            lengths.append(len(late))
    assert not armed[0] and out[0].reinitialised
    err = np.array([float((r.output_points[:16].double() - _landmarks(subj, walk[33 + i]).double()).norm(dim=-1)
                          .mean()) for i, r in enumerate(out)])
    return out, err, lengths


def test_a_wrong_reacquisition_is_mended_by_the_track_back(skel, monkeypatch):
    """Without the settle-back the first re-acquired frames show the wrong arm until the track finds it (the first
    two over 20 mm off); with it, once the track has held 1 s (30 frames at 30 fps) those 30 frames are tracked
    again backwards from there and replace the forward ones (one revision of 30 frames): the first two within 15
    mm of the truth, every frame within 40 mm, and the frames after the same track as without."""
    _, plain, none = _track_reacquired(skel, monkeypatch, 0.0)
    assert none == [] and (plain[:2] > 0.02).all(), plain[:5]
    _, settled, lengths = _track_reacquired(skel, monkeypatch, 1.0)
    assert lengths == [30], lengths
    assert (settled[:2] < 0.015).all() and settled.max() < 0.04, settled
    np.testing.assert_allclose(settled[30:], plain[30:], atol=2e-3)


def test_a_wrong_reacquisition_near_the_end_is_tracked_back_when_the_sequence_ends(skel, monkeypatch):
    """The same wrong re-acquisition 12 frames before the sequence ends (under the 1 s the track back waits for):
    without :meth:`MarkerlessTracker.finish` its first frames stay wrong; with it the 12 frames are tracked back
    from the last one (one revision of 12 frames) and the first two come within 15 mm of the truth."""
    _, plain, none = _track_reacquired(skel, monkeypatch, 1.0, frames=12)
    assert none == [] and (plain[:2] > 0.02).all(), plain
    _, ended, lengths = _track_reacquired(skel, monkeypatch, 1.0, frames=12, finish=True)
    assert lengths == [12], lengths
    assert (ended[:2] < 0.015).all() and ended.max() < 0.04, ended


@pytest.mark.parametrize("still", [False, True])
def test_a_race_still_on_when_the_sequence_ends(skel, monkeypatch, still):
    """The search's answer forced to face backwards and the sequence ended 12 frames later, before the 0.5 s
    start race (15 frames): :meth:`MarkerlessTracker.finish` decides the race on those frames where the body moved in
    them (a walker: every frame within 50 mm of the truth, none turned round, as without it the frames stay turned
    round); where it stood still (a still body looks the same turned round) the search's start stays and the race
    is dropped."""
    search_turned_round(monkeypatch)
    subj = skel.scaled_to_height(1.8)
    blobs = BlobModel.from_config(subj)
    walk = procedural_motion(subj, "walk", 1.0, 30, starfish_s=0.0)[10:22]
    if still:
        walk = walk[:1].repeat(12, 1)
    errors = []
    for finish in (False, True):
        tracker = MarkerlessTracker(skel, TrackerConfig(start_race_s=0.5, settle_back_s=1.0))
        tracker.set_frame_rate(30.0)
        out = []
        for t in range(walk.shape[0]):
            out.append(tracker.step(_observation(subj, blobs, walk[t])))
            apply_revised(out, tracker.take_revised())
        assert tracker.racing
        if finish:
            tracker.finish()
            apply_revised(out, tracker.take_revised())
            assert not tracker.racing and not tracker.settling
        errors.append(np.array([float((r.output_points[:16].double() - _landmarks(subj, walk[t]).double())
                                      .norm(dim=-1).mean()) for t, r in enumerate(out)]))
    plain, ended = errors
    assert plain.min() > 0.1, plain  # turned round
    if still:  # the search's start stays (tracked back over the 12 frames, still turned round)
        assert ended.min() > 0.1, ended
    else:
        assert ended.max() < 0.05, ended


def test_a_race_decided_on_the_frame_of_the_track_back_keeps_its_revision(skel, monkeypatch):
    """The search's answer forced to face backwards on a walker who stands still for 1 s first: the start race waits
    for the body to move, so it is decided on the frame where the start's frames are also tracked back
    (settle_back_s 1 s < the race). The race's revision (the right way round) and the splice both reach the caller:
    every frame within 50 mm of the truth (the walk's forward kinematics), none left turned round."""
    search_turned_round(monkeypatch)
    subj = skel.scaled_to_height(1.8)
    blobs = BlobModel.from_config(subj)
    walk = procedural_motion(subj, "walk", 1.5, 30, starfish_s=0.0)
    walk = torch.cat([walk[:1].repeat(30, 1), walk])  # standing still for 1 s, then walking
    tracker = MarkerlessTracker(skel, TrackerConfig(start_race_s=0.5, settle_back_s=1.0))
    tracker.set_frame_rate(30.0)
    out, lengths = [], []
    for t in range(walk.shape[0]):
        out.append(tracker.step(_observation(subj, blobs, walk[t])))
        late = tracker.take_revised()
        apply_revised(out, late)
        if late:
            lengths.append((t, len(late)))
    assert len(lengths) == 1 and lengths[0][1] == lengths[0][0] + 1, lengths  # one revision, from the first frame
    assert not tracker.racing and not tracker.settling
    err = np.array([float((r.output_points[:16].double() - _landmarks(subj, walk[t]).double()).norm(dim=-1).mean())
                    for t, r in enumerate(out)])
    assert err.max() < 0.05, err


def test_the_splice_is_the_least_total_cost_against_a_plain_loop():
    """splice_index against every k tried in a plain loop (the latest of equal totals), on random costs and ties."""
    from torchtrack.tracking.settle import splice_index

    gen = torch.Generator().manual_seed(3)
    cases = [torch.rand(2, n, generator=gen, dtype=torch.float64) for n in (1, 2, 7, 30)]
    cases.append(torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]], dtype=torch.float64))  # ties: no revision
    cases.append(torch.tensor([[5.0, 1.0], [2.0, 3.0]], dtype=torch.float64))
    for f, b in cases:
        totals = [float(f[:k].sum() + b[k:].sum()) for k in range(len(f) + 1)]
        want = max(k for k, x in enumerate(totals) if x <= min(totals) + 1e-12)
        assert splice_index(f, b) == want, (f, b, totals)
