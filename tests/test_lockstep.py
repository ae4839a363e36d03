"""Several sequences tracked in lockstep (torchtrack/tracking/lockstep.py): each gets the track it gets alone."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import pytest
import torch

from torchtrack.blobs import BlobModel
from torchtrack.checks import InputError
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import procedural_motion
from torchtrack.tracking.lockstep import Lockstep
from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
from torchtrack.tracking.observation import VoxelObservation

from conftest import DEVICES, voxelised_observation


def _double(obs: VoxelObservation, device: str) -> VoxelObservation:
    return replace(obs, points=obs.points.double().to(device), sizes=obs.sizes.double().to(device),
                   weights=obs.weights.double().to(device), colours=obs.colours.double().to(device),
                   cameras_valid=obs.cameras_valid.to(device))


def _sequences(skel: Skeleton, device: str) -> list[list[VoxelObservation]]:
    """Three sequences of voxelised bodies (float64): a walk with a frame of nobody; a walk whose subject comes
    back mid-squat turned round 0.5 m away (the tracker diverges, then re-acquires); a shorter kick of a smaller
    subject with a frame of too few voxels for a person."""
    names = list(skel.dof_names)
    out = []
    subj = skel.scaled_to_height(1.80)
    blobs = BlobModel.from_config(subj)
    walk = procedural_motion(subj, "walk", 0.3, 30, starfish_s=0.2)
    seq = [voxelised_observation(subj, blobs, a) for a in walk]
    seq[9] = replace(seq[9], points=seq[9].points[:0], sizes=seq[9].sizes[:0], weights=seq[9].weights[:0],
                     colours=seq[9].colours[:0])
    out.append(seq)
    subj = skel.scaled_to_height(1.72)
    blobs = BlobModel.from_config(subj)
    walk = procedural_motion(subj, "walk", 0.2, 30, starfish_s=0.2)
    back = procedural_motion(subj, "squat", 1.0, 30, starfish_s=0.0)[14].clone()
    back[names.index("root_rz")] = float(walk[-1, names.index("root_rz")]) + math.radians(150)
    back[names.index("root_tx")] += 0.5
    out.append([voxelised_observation(subj, blobs, a) for a in walk] + [voxelised_observation(subj, blobs, back)] * 5)
    subj = skel.scaled_to_height(1.62)
    blobs = BlobModel.from_config(subj)
    seq = [voxelised_observation(subj, blobs, a) for a in procedural_motion(subj, "kick", 0.2, 30, starfish_s=0.2)]
    # a few voxels, too little volume for a person: the batched step takes it, the routine test drops it
    seq[9] = replace(seq[9], points=seq[9].points[:40], sizes=seq[9].sizes[:40], weights=seq[9].weights[:40],
                     colours=seq[9].colours[:40])
    out.append(seq)
    return [[_double(o, device) for o in seq] for seq in out]


def _in_lockstep(trackers: list[MarkerlessTracker], seqs: list[list[VoxelObservation]],
                 revise: Callable[[list, MarkerlessTracker], None] | None = None) -> list[list]:
    """Each sequence's results, its tracker stepped in lockstep with the others' (a shorter one ends early); with
    ``revise``, each track revised after each frame (the tracker's take_revised)."""
    lockstep = Lockstep(trackers)
    got: list[list] = [[] for _ in seqs]
    for k in range(max(len(s) for s in seqs)):
        results, errors = lockstep.step({i: s[k] for i, s in enumerate(seqs) if k < len(s)})
        assert not errors
        for i, res in results.items():
            got[i].append(res)
            if revise is not None:
                revise(got[i], trackers[i])
    return got


@pytest.mark.parametrize("device", DEVICES)
def test_sequences_in_lockstep_are_tracked_as_each_alone(device, monkeypatch):
    """Three different sequences (one with a frame of nobody, one that re-acquires, one shorter) in lockstep, and
    each alone, in float64: the same output points within 1e-6 m on every frame (float32's rounding, which the
    batch's padding changes, grows along a track like any perturbation: the double run checks the arithmetic).
    The starts and re-acquisitions, which each tracker runs on its own either way, go without the whole-state
    search (the starfish start; re-acquisition from the last pose's four headings) to keep the test short."""
    monkeypatch.setattr(MarkerlessTracker, "_searched", lambda self, obs: None)
    skel = Skeleton.from_urdf().to(device)
    seqs = _sequences(Skeleton.from_urdf(), device)  # the bodies voxelised on the CPU, then moved
    config = TrackerConfig(start="starfish")
    alone = []
    for seq in seqs:
        tracker = MarkerlessTracker(skel, config)
        tracker.set_frame_rate(30.0)
        alone.append([tracker.step(o) for o in seq])
    trackers = [MarkerlessTracker(skel, config) for _ in seqs]
    for t in trackers:
        t.set_frame_rate(30.0)
    got = _in_lockstep(trackers, seqs)
    for i, seq in enumerate(seqs):
        assert len(got[i]) == len(seq)
        for k, (g, a) in enumerate(zip(got[i], alone[i])):
            assert (g.valid, g.reinitialised) == (a.valid, a.reinitialised), (i, k)
            torch.testing.assert_close(g.output_points, a.output_points, rtol=0, atol=1e-6, msg=f"seq {i} frame {k}")
    assert not alone[0][9].valid and alone[0][-1].valid and alone[0][10].reinitialised  # nobody there, then found again
    reacquired = [k for k, r in enumerate(alone[1]) if r.reinitialised and k > 0]
    assert reacquired and not alone[1][reacquired[0] - 1].valid and alone[1][-1].valid  # lost, then re-acquired
    assert len(seqs[2]) < len(seqs[0]) and not alone[2][9].valid and alone[2][-1].valid


def test_lockstep_refuses_trackers_of_different_settings():
    skel = Skeleton.from_urdf()
    with pytest.raises(InputError, match="settings differ"):
        Lockstep([MarkerlessTracker(skel), MarkerlessTracker(skel, TrackerConfig(refinements=2))])
    with pytest.raises(InputError, match="no trackers"):
        Lockstep([])


def test_the_per_frame_core_reads_no_files_and_logs_nothing():
    """The per-frame core (the step, EM, goals, IK, the trackers and their lockstep) imports no reader, logger,
    renderer or observation model: drivers hand it its frames."""
    import subprocess
    import sys

    code = ("import sys; import torchtrack.tracking.lockstep, torchtrack.tracking.markerless; "
            "print(' '.join(m for m in sys.modules if m.startswith(('torchtrack.io', 'torchtrack.logging', "
            "'torchtrack.synth', 'torchtrack.occupancy'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", out.stdout


def test_frames_held_in_the_images_are_the_same_in_lockstep_as_alone():
    """``image_hold_s`` in lockstep, each camera's foreground the body's true silhouette (clearance.body_masks): a
    walker crossing the observed volume's side (x = 2.4 m) out of it, held in the images (each tracker's own
    step); a walker who comes back mid-squat turned round 0.5 m away, whose diverging frames (the batched step)
    are held back in their images once the body is re-acquired (take_revised); one walking in the middle. Every
    frame and every revision the same within 1e-6 m in lockstep as alone (float64 voxels)."""
    from torchtrack.synth.sequence import RigConfig, make_ring_rig
    from torchtrack.tracking.clearance import body_masks
    from torchtrack.tracking.voxels import ViewSilhouettes

    skel = Skeleton.from_urdf()
    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    names = list(skel.dof_names)
    rig = make_ring_rig(RigConfig(num_cameras=8, width=320, height=240, radius_m=4.5)).float()

    def observed(a: torch.Tensor) -> VoxelObservation:
        obs = _double(voxelised_observation(subj, blobs, a, cameras=8), "cpu")
        keep = obs.points[:, 0] < 2.4
        fg = body_masks(rig, subj, a[None], blobs=blobs)[0].float()
        return replace(obs, points=obs.points[keep], sizes=obs.sizes[keep], weights=obs.weights[keep],
                       colours=obs.colours[keep], volume_m=((-2.4, -2.4, 0.0), (2.4, 2.4, 2.1)),
                       silhouettes=ViewSilhouettes.from_evidence(2 * fg - 1, rig))

    starts, frames = [], []
    for x0, dx, seconds in ((2.2, 0.05, 0.6), (-0.6, 0.03, 0.3), (-0.6, 0.03, 0.6)):
        walk = procedural_motion(subj, "walk", seconds, 30, starfish_s=0.0)
        walk[:, names.index("root_rz")] = 0.0
        walk[:, names.index("root_ty")] = 0.0
        walk[:, names.index("root_tx")] = x0 + dx * torch.arange(walk.shape[0]).to(walk)
        seq = [observed(a) for a in walk[1:]]
        if seconds < 0.5:  # back mid-squat, turned round 1 m on
            back = procedural_motion(subj, "squat", 1.0, 30, starfish_s=0.0)[14].clone()
            back[names.index("root_rz")] = math.radians(150)
            back[names.index("root_tx")] = float(walk[-1, names.index("root_tx")]) + 1.0
            seq += [observed(back)] * 5
        starts.append(walk[0].double())
        frames.append(seq)
    config = TrackerConfig(image_hold_s=1.0, start_race_s=0.0, settle_back_s=0.0)

    def started() -> list[MarkerlessTracker]:
        out = []
        for a in starts:
            tracker = MarkerlessTracker(skel, config)
            tracker.set_frame_rate(30.0)
            tracker.initialize_from_pose(a, 1.75)
            out.append(tracker)
        return out

    def revise(track: list, tracker: MarkerlessTracker) -> None:
        revised = tracker.take_revised()
        if revised:
            track[-len(revised):] = [r for r, _ in revised]

    alone = []
    for tracker, seq in zip(started(), frames):
        track = []
        for obs in seq:
            track.append(tracker.step(obs))
            revise(track, tracker)
        alone.append(track)
    got = _in_lockstep(started(), frames, revise)
    for i in range(len(frames)):
        assert len(got[i]) == len(alone[i]) == len(frames[i])
        for k, (g, a) in enumerate(zip(got[i], alone[i])):
            assert (g.valid, g.reinitialised) == (a.valid, a.reinitialised), (i, k)
            torch.testing.assert_close(g.output_points, a.output_points, rtol=0, atol=1e-6, msg=f"seq {i} frame {k}")
    hold = config.image_hold_confidence
    held = [[bool(r.valid and torch.all(r.confidence == hold)) for r in track] for track in alone]
    assert sum(held[0]) >= 5 and held[0][-1]  # out of the volume: held to the end
    back = next(k for k, r in enumerate(alone[1]) if r.reinitialised)
    assert back > len(frames[1]) - 5 and held[1][back - 1]  # re-acquired, the frame before it held back
    assert not any(held[2]) and all(r.valid for r in alone[2])  # in the middle: the batched step throughout


def test_voxel_rows_are_padded_as_pad_sequence_pads_them():
    """``pad_rows`` (one copy for all rows) against torch's ``pad_sequence``: rows of different lengths, an empty
    one, bool rows, rows of two dtypes (promoted, as ``torch.cat``), all of one length, one row."""
    from torch.nn.utils.rnn import pad_sequence

    from torchtrack.tracking.step import pad_rows

    g = torch.Generator().manual_seed(0)
    for rows, value in (([torch.rand(n, 4, 3, generator=g) for n in (5, 0, 7, 2)], math.nan),
                        ([torch.rand(n, 3, generator=g) > 0.5 for n in (3, 6)], False),
                        ([torch.rand(4, generator=g), torch.rand(6, generator=g).double()], 0.0),
                        ([torch.rand(4, 2, generator=g) for _ in range(3)], 0.0),
                        ([torch.rand(4, 2, generator=g)], 0.0)):
        dtype = torch.float64 if any(r.dtype == torch.float64 for r in rows) else rows[0].dtype
        expected = pad_sequence([r.to(dtype) for r in rows], batch_first=True, padding_value=value)
        got = pad_rows(rows, value)
        assert got.dtype == dtype and got.shape == expected.shape
        torch.testing.assert_close(got, expected, rtol=0, atol=0, equal_nan=True)
