"""Voxel observations (torchtrack.tracking.voxels): the volume share of an ellipsoid, pooled cells, connected
parts, split observations, each against a grid count or a plain loop.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchtrack.blobs import BlobModel
from torchtrack.conventions import LANDMARKS
from torchtrack.skeleton import Skeleton
from torchtrack.tracking.markerless import MarkerlessTracker
from torchtrack.synth.motion import procedural_motion
from torchtrack.tracking.observation import VoxelObservation

from conftest import landmarks_of as _landmarks, track_voxelised as _track, voxelise as _voxelise, \
    voxelised_observation as _observation

torch.set_grad_enabled(False)


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


def test_the_share_of_an_ellipsoid_out_of_the_volume_matches_a_grid_count():
    """``VoxelObservation.outside`` against the nodes of a 4 mm grid inside tilted ellipsoids counted beyond each
    side of the volume, its top, and below its floor (no cut)."""
    box = ((-1.0, -1.0, 0.0), (1.0, 1.0, 2.0))
    obs = VoxelObservation(torch.zeros(0, 3), torch.zeros(0), torch.zeros(0), torch.zeros(0, 1, 3),
                           torch.ones(1, dtype=torch.bool), volume_m=box)
    R = torch.from_numpy(Rotation.from_euler("xyz", [0.3, -0.5, 0.9]).as_matrix())
    semi = torch.tensor([0.2, 0.08, 0.06], dtype=torch.float64)
    cov = R @ torch.diag(semi ** 2 / 5.0) @ R.T
    centres = torch.tensor([[0.0, 0.0, 1.0], [0.95, 0.2, 1.0], [-0.2, -1.05, 0.9], [0.1, 0.3, 1.9],
                            [0.0, 0.0, 0.02], [1.3, 0.0, 1.0]], dtype=torch.float64)
    got = obs.outside(centres, cov.expand(len(centres), 3, 3))
    lo, hi = torch.tensor(box[0], dtype=torch.float64), torch.tensor(box[1], dtype=torch.float64)
    for c, share in zip(centres, got):
        pts, _ = _voxelise(c[None], R[None], semi[None], voxel=0.004)
        out = ((pts[:, :2] < lo[:2]) | (pts[:, :2] > hi[:2])).any(-1) | (pts[:, 2] > hi[2])
        assert abs(float(share) - float(out.double().mean())) < 0.01, (c, float(share), float(out.double().mean()))
    assert float(got[0]) == 0.0 and float(got[4]) == 0.0 and float(got[5]) == 1.0
    unbounded = dataclasses.replace(obs, volume_m=None)
    assert not bool(unbounded.outside(centres, cov.expand(len(centres), 3, 3)).any())


def test_a_blob_mostly_out_of_the_volume_gives_no_goals(skel, monkeypatch):
    """A starfish whose right forearm the volume's side cuts in the middle (nothing observed beyond it): the
    forearm's and hand's blobs, mostly outside, give no goals (the wrist's confidence 0, the arm kept where the
    prediction puts it), the upper arm's, a little outside, still does. With every blob's goals kept the
    half-forearm gives the wrist a goal (confidence 0.19)."""
    import torchtrack.tracking.step as step

    subj = skel.scaled_to_height(1.80)
    blobs = BlobModel.from_config(subj)
    pose = subj.starfish_angles()
    truth = _landmarks(subj, pose)
    elbow, wrist = (LANDMARKS.index(n) for n in ("r_elbow", "r_wrist"))
    edge = float(0.5 * (truth[elbow, 1] + truth[wrist, 1]))  # the arms lie along y, the right one towards -y
    full = _observation(subj, blobs, pose)
    keep = full.points[:, 1] >= edge
    obs = VoxelObservation(full.points[keep], full.sizes[keep], full.weights[keep], full.colours[keep],
                           full.cameras_valid, volume_m=((-3.0, edge, 0.0), (3.0, 3.0, 2.5)))

    def run():
        tracker = MarkerlessTracker(skel)
        tracker.initialize_from_pose(pose, 1.80)
        for _ in range(4):
            r = tracker.step(obs)
        return r

    r = run()
    assert float(r.confidence[wrist]) == 0.0 and float(r.confidence[elbow]) > 0.3
    assert float((r.output_points[wrist] - truth[wrist]).norm()) < 0.02
    monkeypatch.setattr(step, "MAX_OUTSIDE", 1.0)
    assert float(run().confidence[wrist]) > 0.1


def test_pooled_observation_matches_a_plain_loop():
    gen = torch.Generator().manual_seed(3)
    N, C = 200, 3
    pts = torch.rand(N, 3, generator=gen, dtype=torch.float64) * 0.2
    sizes = torch.full((N,), 0.015, dtype=torch.float64)
    w = torch.rand(N, generator=gen, dtype=torch.float64)
    col = torch.rand(N, C, 3, generator=gen, dtype=torch.float64)
    col[torch.rand(N, C, generator=gen) < 0.3] = float("nan")
    obs = VoxelObservation(pts, sizes, w, col, torch.ones(C, dtype=torch.bool))
    pooled = obs.pooled(0.05)
    cells: dict[tuple, list[int]] = {}
    for n in range(N):
        cells.setdefault(tuple(int(v) for v in torch.floor(pts[n] / 0.05)), []).append(n)
    assert pooled.num_voxels == len(cells)
    assert abs(float(pooled.weights.sum()) - float(w.sum())) < 1e-9
    for members in cells.values():
        ref_p = sum(w[n] * pts[n] for n in members) / sum(w[n] for n in members)
        m = int((pooled.points - ref_p).norm(dim=-1).argmin())
        assert float((pooled.points[m] - ref_p).norm()) < 1e-12
        assert abs(float(pooled.weights[m]) - float(sum(w[n] for n in members))) < 1e-12
        assert abs(float(pooled.sizes[m]) - 0.015 * len(members) ** (1 / 3)) < 1e-12  # same volume as its voxels
        for c in range(C):
            seen = [n for n in members if not torch.isnan(col[n, c]).any()]
            if seen:
                ref_c = sum(w[n] * col[n, c] for n in seen) / sum(w[n] for n in seen)
                assert torch.allclose(pooled.colours[m, c], ref_c, atol=1e-12)
            else:
                assert bool(torch.isnan(pooled.colours[m, c]).all())


def test_parts_are_the_connected_cells_a_plain_search_finds():
    """Random occupied cells, each a voxel filling its cell: the parts are the groups a breadth-first search over
    cells touching by a face, an edge or a corner finds, numbered largest first, with their volumes and heights."""
    gen = torch.Generator().manual_seed(5)
    cell = 0.06
    keys = torch.randint(0, 8, (120, 3), generator=gen).unique(dim=0)
    N = keys.shape[0]
    pts = (keys.double() + 0.5) * cell
    sizes = torch.full((N,), cell, dtype=torch.float64)
    obs = VoxelObservation(pts, sizes, sizes ** 3, torch.zeros(N, 1, 3, dtype=torch.float64),
                           torch.ones(1, dtype=torch.bool))
    part, volume, span = obs.parts(cell)
    ref = [-1] * N
    cells = [tuple(k) for k in keys.tolist()]
    for seed in range(N):
        if ref[seed] >= 0:
            continue
        ref[seed], queue = seed, [seed]
        while queue:
            a = queue.pop()
            for b in range(N):
                if ref[b] < 0 and max(abs(u - v) for u, v in zip(cells[a], cells[b])) <= 1:
                    ref[b] = seed
                    queue.append(b)
    groups: dict[int, list[int]] = {}
    for n, r in enumerate(ref):
        groups.setdefault(r, []).append(n)
    assert len(groups) > 3  # the draw has several parts
    assert volume.shape[0] == len(groups)
    for members in groups.values():
        assert len({int(part[n]) for n in members}) == 1  # one part per group, one group per part
        k = int(part[members[0]])
        assert abs(float(volume[k]) - len(members) * cell ** 3) < 1e-12
        z = pts[members, 2]
        assert float(span[k, 0]) == pytest.approx(float(z.min()) - cell / 2)
        assert float(span[k, 1]) == pytest.approx(float(z.max()) + cell / 2)
    assert bool((volume[1:] <= volume[:-1]).all())


def test_a_large_voxel_joins_the_parts_it_overlaps():
    """Two 3 cm voxels 15 cm apart are two parts; a 12 cm voxel between them (a hull's coarse interior cube)
    overlaps both voxels' cells and makes them one."""
    pts = torch.tensor([[0.015, 0.015, 0.015], [0.165, 0.015, 0.015], [0.09, 0.015, 0.015]])
    sizes = torch.tensor([0.03, 0.03, 0.12])
    colours = torch.zeros(3, 1, 3)
    apart = VoxelObservation(pts[:2], sizes[:2], sizes[:2] ** 3, colours[:2], torch.ones(1, dtype=torch.bool))
    joined = VoxelObservation(pts, sizes, sizes ** 3, colours, torch.ones(1, dtype=torch.bool))
    assert apart.parts(0.06)[1].shape[0] == 2
    part, volume, _ = joined.parts(0.06)
    assert volume.shape[0] == 1 and part.tolist() == [0, 0, 0]


def test_split_observation_matches_a_plain_loop():
    """Hull-like voxels of 1.5 to 12 cm split to at most 3 cm: every voxel over 3 cm becomes the n^3 cubes of a
    loop over its cells, each with 1 / n^3 of its weight and its colours; the others stay; weight and volume kept."""
    gen = torch.Generator().manual_seed(5)
    N, C = 40, 2
    pts = torch.rand(N, 3, generator=gen, dtype=torch.float64)
    sizes = torch.tensor([0.015, 0.03, 0.06, 0.12], dtype=torch.float64)[torch.randint(0, 4, (N,), generator=gen)]
    w = sizes ** 3 * torch.rand(N, generator=gen, dtype=torch.float64)
    col = torch.rand(N, C, 3, generator=gen, dtype=torch.float64)
    col[0, 1] = float("nan")
    obs = VoxelObservation(pts, sizes, w, col, torch.ones(C, dtype=torch.bool))
    out = obs.split(0.03)
    ref = []
    for v in range(N):
        n = max(1, math.ceil(round(float(sizes[v]) / 0.03, 9)))
        for i in range(n):
            for j in range(n):
                for k in range(n):
                    corner = pts[v] - sizes[v] / 2
                    ref.append((corner + (torch.tensor([i, j, k], dtype=torch.float64) + 0.5) * sizes[v] / n,
                                float(sizes[v]) / n, float(w[v]) / n ** 3, col[v]))
    assert out.num_voxels == len(ref) and out.num_observed == N
    for p, size, weight, colour in ref:
        m = int((out.points - p).norm(dim=-1).argmin())
        assert float((out.points[m] - p).norm()) < 1e-12
        assert abs(float(out.sizes[m]) - size) < 1e-12 and abs(float(out.weights[m]) - weight) < 1e-15
        assert torch.equal(torch.isnan(out.colours[m]), torch.isnan(colour))
        assert torch.allclose(torch.nan_to_num(out.colours[m]), torch.nan_to_num(colour), atol=0)
    assert abs(float(out.weights.sum()) - float(w.sum())) < 1e-12
    assert abs(out.volume_m3() - obs.volume_m3()) < 1e-12
    assert obs.split(0.2) is obs  # nothing to split


def test_the_floor_band_takes_the_weight_of_the_voxels_under_it_only():
    """``without_floor_band``: the voxels whose centres lie under the band over the volume's floor weigh nothing,
    the others as before, every voxel kept; no volume, no band or nothing above it: the observation as it is."""
    z = torch.tensor([0.015, 0.029, 0.045, 0.5, 1.2])
    pts = torch.stack([torch.zeros(5), torch.zeros(5), z + 0.1], -1)  # the volume's floor at z = 0.1
    w = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0])
    obs = VoxelObservation(pts, torch.full((5,), 0.03), w, torch.zeros(5, 2, 3), torch.ones(2, dtype=torch.bool),
                           volume_m=((-1.0, -1.0, 0.1), (1.0, 1.0, 2.1)))
    out = obs.without_floor_band(0.03)
    assert out.weights.tolist() == [0.0, 0.0, 3.0, 4.0, 5.0]
    assert torch.equal(out.points, obs.points) and out.height_span() == obs.height_span()
    assert obs.without_floor_band(0.0) is obs
    assert dataclasses.replace(obs, volume_m=None).without_floor_band(0.03).weights.tolist() == w.tolist()
    # nothing above it: no weight would be left, so the weights stay as they were (chosen on the device)
    assert torch.equal(obs.without_floor_band(2.0).weights, w)


def test_the_floor_band_by_default_from_seven_cameras_and_as_set_otherwise():
    from torchtrack.checks import InputError
    from torchtrack.tracking.config import FLOOR_BAND_M, FLOOR_BAND_MIN_CAMERAS, TrackerConfig

    assert TrackerConfig().floor_band(FLOOR_BAND_MIN_CAMERAS) == FLOOR_BAND_M > 0
    assert TrackerConfig().floor_band(FLOOR_BAND_MIN_CAMERAS - 1) == 0.0
    assert TrackerConfig(floor_band_m=0.05).floor_band(4) == 0.05
    assert TrackerConfig(floor_band_m=0).floor_band(12) == 0.0
    with pytest.raises(InputError, match="floor_band_m"):
        TrackerConfig(floor_band_m=-0.01)


def test_the_floor_band_keeps_a_floor_shadows_ghost_from_pulling_the_feet_down():
    """A walk's voxelised body over a floor shadow's ghost (a 3 cm layer of voxels on the floor, 0.9 m across under
    the body, as a shadow that every view takes for foreground gives): the ghost drags the feet into the floor
    unless the floor band takes its weight; with it the ankles are tracked as on a clean floor (ground truth)."""
    skel = Skeleton.from_urdf()
    subj = skel.scaled_to_height(1.80)
    ankles = [LANDMARKS.index("l_ankle"), LANDMARKS.index("r_ankle")]
    g = torch.arange(-0.45, 0.45, 0.03) + 0.015
    pad = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    pad = pad[pad.norm(dim=-1) <= 0.45]

    def with_ghost(t, obs):  # the ghost under the body's centroid, on the floor of a bounded volume
        ghost = torch.cat([pad + obs.points[:, :2].mean(0), torch.full((pad.shape[0], 1), 0.015)], -1)
        n = ghost.shape[0]
        return VoxelObservation(torch.cat([obs.points, ghost]), torch.cat([obs.sizes, obs.sizes[:1].expand(n)]),
                                torch.cat([obs.weights, obs.weights[:1].expand(n)]),
                                torch.cat([obs.colours, torch.full((n, *obs.colours.shape[1:]), 0.3)]),
                                obs.cameras_valid, volume_m=((-3.0, -3.0, 0.0), (3.0, 3.0, 2.1)))

    def ankle_errors(band):
        tracker = MarkerlessTracker(skel, dataclasses.replace(MarkerlessTracker(skel).config, floor_band_m=band))
        _, _, results = _track(skel, "walk", 30, tracker=tracker, edit=with_ghost)
        truth = procedural_motion(subj, "walk", 1.0, 30, starfish_s=0.3)
        assert len(results) == truth.shape[0]
        return np.array([float((r.output_points[ankles] - _landmarks(subj, truth[t])[ankles]).norm(dim=-1).mean())
                         for t, r in enumerate(results) if t >= 10 and r.valid])

    with_band, without = ankle_errors(0.03), ankle_errors(0.0)
    assert len(with_band) == len(without) > 15
    assert with_band.mean() < 0.03, with_band
    assert without.mean() > 0.05, without
