"""The start search's selection (torchtrack.tracking.search)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from torchtrack.tracking.search import _top_both_ways, ellipsoid_distance2


def _reference(score: list[float], heading: list[float], n: int) -> set[int]:
    """A plain loop: walk the hypotheses best first; each joins its side (facing within 90 deg of the best's heading,
    or not) while that side has fewer than its share (half of ``n`` ahead, rounded up, the rest behind); then the
    best of those left until there are ``n``."""
    order = sorted(range(len(score)), key=lambda i: -score[i])
    h0 = heading[order[0]]

    def ahead(i: int) -> bool:
        d = (heading[i] - h0) % (2 * math.pi)
        return min(d, 2 * math.pi - d) < 0.5 * math.pi

    n_ahead = min(n - n // 2, sum(ahead(i) for i in order))
    n_behind = min(n - n_ahead, sum(not ahead(i) for i in order))
    got, a, b = [], 0, 0
    for i in order:
        if ahead(i) and a < n_ahead:
            got.append(i)
            a += 1
        elif not ahead(i) and b < n_behind:
            got.append(i)
            b += 1
    for i in order:
        if len(got) >= n:
            break
        if i not in got:
            got.append(i)
    return set(got)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("n", [1, 4, 7, 16])
def test_the_kept_hypotheses_face_both_ways_as_a_plain_loop_picks_them(seed, n):
    g = torch.Generator().manual_seed(seed)
    m = 40
    score = torch.rand(m, generator=g)
    # mostly facing one way, as an annealed search's pool does; seed 0 all one way (the rest from that side)
    heading = 0.3 * torch.randn(m, generator=g) + (math.pi * (torch.rand(m, generator=g) < 0.2) if seed else 0.0)
    heading = heading + 4 * math.pi * torch.randint(-1, 2, (m,), generator=g)  # headings not wrapped
    got = _top_both_ways(score, heading, n)
    assert got.shape[0] == n and len(set(got.tolist())) == n
    assert set(got.tolist()) == _reference(score.tolist(), heading.tolist(), n)
    assert int(score.argmax()) in got.tolist()  # the best is always kept


def test_a_short_side_leaves_its_share_to_the_other():
    """Two hypotheses face the best's way, ten away: n = 8 keeps both and the best six facing away; n = 20 all."""
    score = torch.tensor([0.9, 0.1] + [0.8 - 0.05 * k for k in range(10)])
    heading = torch.tensor([0.2, -0.3] + [math.pi + 0.1 * k for k in range(10)])
    assert set(_top_both_ways(score, heading, 8).tolist()) == {0, 1, 2, 3, 4, 5, 6, 7}
    assert sorted(_top_both_ways(score, heading, 20).tolist()) == list(range(12))


@pytest.mark.parametrize("seed", range(3))
def test_ellipsoid_distance2_matches_a_plain_loop(seed):
    """The quadric product against each point turned into each ellipsoid's axes and divided by its semi-axes, in
    float64 one pair at a time; body-sized ellipsoids 2-3 m from the origin, as in a room."""
    g = torch.Generator().manual_seed(seed)
    H, K, N = 3, 5, 40
    centres = torch.tensor([2.0, -1.5, 1.0]) + 0.4 * torch.randn(H, K, 3, generator=g)
    R = torch.linalg.qr(torch.randn(H, K, 3, 3, generator=g))[0]
    semi = 0.03 + 0.2 * torch.rand(H, K, 3, generator=g)
    points = centres.reshape(-1, 3)[torch.randint(H * K, (N,), generator=g)] + 0.15 * torch.randn(N, 3, generator=g)
    got = ellipsoid_distance2(points, centres, R, semi)
    want = torch.empty(N, H, K, dtype=torch.float64)
    for n in range(N):
        for h in range(H):
            for k in range(K):
                local = R[h, k].double().T @ (points[n] - centres[h, k]).double() / semi[h, k].double()
                want[n, h, k] = float(local @ local)
    assert torch.allclose(got.double(), want, rtol=1e-4, atol=1e-3)
    assert ((got <= 1) == (want <= 1)).float().mean() > 0.99  # inside tests agree but at the boundary's rounding


@pytest.mark.parametrize("case", range(3))
def test_the_limb_sweep_finds_limbs_off_the_prior(case):
    """A body whose arms and a leg are off every pose of the structured prior (each joint drawn near an in-between
    value), at three headings: stages 1-2 and the limb sweep alone (no annealing) land within 50 mm of it (ground
    truth: the pose's forward kinematics), and at least 10 mm nearer than without the sweep."""
    from conftest import voxelised_observation
    from torchtrack.blobs import BlobModel
    from torchtrack.conventions import LANDMARKS
    from torchtrack.skeleton import Skeleton
    from torchtrack.tracking.search import SearchConfig, search_pose

    skel = Skeleton.from_urdf()
    names, idx = list(skel.dof_names), [list(skel.output_names).index(n) for n in LANDMARKS]
    gen = torch.Generator().manual_seed(case)
    truth = torch.zeros(skel.num_dofs, dtype=torch.float64)
    for dof, value in {"l_shoulder_flex": 0.9, "l_shoulder_abd": 0.35, "l_elbow_flex": 1.1, "r_shoulder_flex": -0.4,
                       "r_shoulder_abd": 0.8, "r_elbow_flex": 0.5, "r_hip_flex": 0.75, "r_knee_flex": 1.2,
                       "l_hip_abd": 0.15}.items():
        truth[names.index(dof)] = value + 0.15 * float(torch.randn(1, generator=gen))
    truth[names.index("root_rz")] = 1.0 + case
    truth = skel.clamp(truth[None])[0]
    subj = skel.scaled_to_height(1.72)
    truth[names.index("root_tz")] -= float(subj.forward(truth[None]).output_points[0, :, 2].min())  # on the floor
    obs = voxelised_observation(subj, BlobModel.from_config(subj), truth)
    want = subj.forward(truth[None]).output_points[0, idx]
    err = {}
    for sweep in (False, True):
        config = SearchConfig(layers=0, sweep=sweep, sweep_voxels=True)  # the voxels score it: no silhouettes
        found = search_pose(obs, skel, BlobModel.from_config(skel), config, torch.Generator().manual_seed(0), n=1)
        body = skel.scaled_to_height(skel.height() * float(found.scale[0]))
        got = body.forward(found.angles[:1].double()).output_points[0, idx]
        err[sweep] = float((got - want).norm(dim=-1).mean())
    assert err[True] < 0.05 and err[True] < err[False] - 0.01, err


def test_a_turned_round_decoy_that_the_coarse_poses_match_better_does_not_take_every_hypothesis(monkeypatch):
    """Where the images score the body, every stage keeps both headings. A closed-form score stands in for the
    images': 1 at the true body's blobs, 0.97 at a decoy (a prior pose, hanging arms and standing legs, facing the
    other way), falling off with the blobs' mean distance from either (their layouts about their means). The
    prior's coarse poses match the decoy best, so a search that kept only the leaders' heading before the annealing
    would never turn round; the true pose (arms at the limb sweep's grid points, off every prior pose; a heading of
    the first stage's) is found within 30 mm, facing its way."""
    from conftest import facing_pair_rig, voxelised_observation
    from torchtrack.blobs import BlobModel
    from torchtrack.conventions import LANDMARKS
    from torchtrack.skeleton import Skeleton
    from torchtrack.tracking import search
    from torchtrack.tracking.observation import ViewSilhouettes

    skel = Skeleton.from_urdf()
    blobs = BlobModel.from_config(skel)
    names, idx = list(skel.dof_names), [list(skel.output_names).index(n) for n in LANDMARKS]
    truth = torch.zeros(skel.num_dofs, dtype=torch.float64)
    for dof, value in {"l_shoulder_flex": 1.2, "l_shoulder_abd": 0.5, "l_elbow_flex": 0.8, "r_shoulder_flex": -0.6,
                       "r_shoulder_abd": 1.0, "r_elbow_flex": 0.1, "root_rz": math.pi / 6}.items():
        truth[names.index(dof)] = value
    truth[names.index("root_tz")] -= float(skel.forward(truth[None]).output_points[0, :, 2].min())  # on the floor
    decoy = torch.zeros_like(truth)
    decoy[names.index("root_rz")] = math.pi / 6 + math.pi
    for i in (names.index("root_tx"), names.index("root_ty"), names.index("root_tz")):
        decoy[i] = truth[i]
    obs = voxelised_observation(skel, blobs, truth)
    rig = facing_pair_rig()  # any cameras with some foreground: the score below does not read them
    obs = dataclasses.replace(obs, cameras_valid=torch.ones(2, dtype=torch.bool),
                              silhouettes=ViewSilhouettes.from_evidence(torch.ones(2, 64, 64), rig, cell_px=4))
    want = [blobs.ellipsoids(skel.forward(a[None]).bone_frames)[0][0].float() for a in (truth, decoy)]

    def score(centres, R, semi, vox, samples, chunk=64):  # the blobs' layout about their mean: the place aside
        c = centres - centres.mean(-2, keepdim=True)
        d_true, d_decoy = ((c - w + w.mean(-2)).norm(dim=-1).mean(-1) for w in want)
        s = torch.maximum(torch.exp(-d_true / 0.05), 0.97 * torch.exp(-d_decoy / 0.05))
        return s, s, s, torch.zeros_like(s)

    monkeypatch.setattr(search, "two_way_score", score)
    config = search.SearchConfig(scale_range=(1.0, 1.0))
    found = search.search_pose(obs, skel, blobs, config, torch.Generator().manual_seed(0), n=1)
    got = skel.forward(found.angles[:1].double()).output_points[0, idx]
    err = float((got - skel.forward(truth[None]).output_points[0, idx]).norm(dim=-1).mean())
    turn = math.remainder(float(found.angles[0, names.index("root_rz")]) - math.pi / 6, 2 * math.pi)
    assert err < 0.03 and abs(turn) < 0.3, (err, turn)


KNEEL = {"l_hip_flex": 0.2, "l_knee_flex": 1.6, "r_hip_flex": 1.0, "r_knee_flex": 1.0}
LUNGE = {"l_hip_flex": 0.9, "l_knee_flex": 1.0, "r_hip_flex": -0.3, "r_knee_flex": 0.6}
ARMS_UP_KNEE_BENT = {"l_shoulder_abd": 2.0, "r_shoulder_abd": 2.0, "l_hip_flex": 0.6, "l_knee_flex": 0.9}


@pytest.mark.parametrize("legs, height", [(KNEEL, 1.55), (KNEEL, 1.90), (LUNGE, 1.55), (ARMS_UP_KNEE_BENT, 1.55)])
def test_each_limb_the_sweep_changes_is_sized_so_the_body_meets_the_voxels_top(legs, height):
    """A kneel, a lunge and raised arms over a bent leg, bodies of 1.55 and 1.90 m: a limb swept into another bend
    changes the body's height, so the sweep sizes each candidate anew. The found body's top (its ellipsoids' highest
    point in closed form, its feet on the voxels' floor) meets the voxels' top within 1 cm, and the true body's top
    within 3 cm (a voxel's size)."""
    from conftest import voxelised_observation
    from torchtrack.blobs import BlobModel
    from torchtrack.skeleton import Skeleton
    from torchtrack.tracking.search import SearchConfig, search_pose

    def top(body, angles):
        blobs = BlobModel.from_config(body)
        c, R = blobs.ellipsoids(body.forward(angles[None].double()).bone_frames)
        return float((c[0, :, 2] + (R[0, :, 2, :] * blobs.semi_axes.double()).norm(dim=-1)).max())

    skel = Skeleton.from_urdf()
    names = list(skel.dof_names)
    truth = torch.zeros(skel.num_dofs, dtype=torch.float64)
    for dof, value in {**legs, "root_rz": 0.7}.items():
        truth[names.index(dof)] = value
    truth = skel.clamp(truth[None])[0]
    subj = skel.scaled_to_height(height)
    truth[names.index("root_tz")] -= float(subj.forward(truth[None]).output_points[0, :, 2].min())  # on the floor
    obs = voxelised_observation(subj, BlobModel.from_config(subj), truth)
    config = SearchConfig(layers=0, sweep=True, sweep_voxels=True)  # stages 1-2 and the sweep, on the voxels
    found = search_pose(obs, skel, BlobModel.from_config(skel), config, torch.Generator().manual_seed(0), n=1)
    body = skel.scaled_to_height(skel.height() * float(found.scale[0]))
    got = top(body, found.angles[0])
    assert abs(got - float(obs.height_span()[1])) < 0.01, (got, obs.height_span())
    assert abs(got - top(subj, truth)) < 0.03, (got, top(subj, truth))


@pytest.mark.parametrize("cameras, in_images", [(4, False), (6, False), (7, True), (8, True)])
def test_finished_bodies_are_compared_in_the_images_from_7_cameras_and_on_the_voxels_below(cameras, in_images):
    """score_states, which compares the start's finished hypotheses, races and held re-acquisitions: with every
    camera's foreground kept, in the images from 7 cameras, on the voxels below. The
    references: the same observation without its foreground (the voxels' score: the voxelised body's own voxels
    all inside its blobs), and all-foreground images, of which a body 4 m away covers under a fifth (the images'
    explained share)."""
    from conftest import voxelised_observation
    from torchtrack.blobs import BlobModel
    from torchtrack.skeleton import Skeleton
    from torchtrack.synth.sequence import RigConfig, make_ring_rig
    from torchtrack.tracking.observation import ViewSilhouettes
    from torchtrack.tracking.search import score_states

    skel = Skeleton.from_urdf()
    blobs = BlobModel.from_config(skel)
    angles = skel.rest_angles().double()
    angles[skel.dof_names.index("root_tz")] -= float(skel.forward(angles[None]).output_points[0, :, 2].min())
    plain = voxelised_observation(skel, blobs, angles, cameras=cameras)
    rig = make_ring_rig(RigConfig(num_cameras=cameras, width=160, height=120, radius_m=4.0)).float()
    kept = dataclasses.replace(plain, silhouettes=ViewSilhouettes.from_evidence(torch.ones(cameras, 120, 160), rig,
                                                                                cell_px=4))
    on_voxels = score_states(plain, skel, blobs, angles[None])
    got = score_states(kept, skel, blobs, angles[None])
    if not in_images:
        for a, b in zip(got, on_voxels):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    else:
        assert float(got[1][0]) < 0.2 and float(on_voxels[1][0]) > 0.9, (got, on_voxels)


def _walker(skel, gen):
    """A walking pose (each joint near a stride's value) at a heading, its feet on the floor, 1.5 m from the
    centre."""
    names = list(skel.dof_names)
    a = torch.zeros(skel.num_dofs, dtype=torch.float64)
    for dof, value in {"l_shoulder_flex": 0.4, "r_shoulder_flex": -0.3, "l_elbow_flex": 0.5, "r_elbow_flex": 0.3,
                       "l_hip_flex": 0.35, "r_hip_flex": -0.2, "l_knee_flex": 0.3, "r_knee_flex": 0.6,
                       "root_rz": 0.7, "root_tx": 1.2, "root_ty": -0.9}.items():
        a[names.index(dof)] = value + 0.1 * float(torch.randn(1, generator=gen))
    a = skel.clamp(a[None])[0]
    a[names.index("root_tz")] -= float(skel.forward(a[None]).output_points[0, :, 2].min())
    return a


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("cameras_shown", [8, 3])
def test_the_search_near_a_prediction_finds_the_body_the_images_show(seed, cameras_shown):
    """search_near_in_images from a prediction 10-14 cm and 0.15 rad off a walker, an arm and a leg 0.25 rad off,
    against the silhouettes of the true body (ground truth: each pixel's ray met with the body's ellipsoids,
    clearance.body_masks, at 320x240 from 4 m): its landmarks land within 50 mm of the truth's on 8 cameras, 90 mm
    on 3 (the others' images unreadable), from about 150 mm, and at least 30 mm nearer than the prediction's; the
    cameras that show the body are counted (all the readable ones)."""
    from torchtrack.blobs import BlobModel
    from torchtrack.conventions import LANDMARKS
    from torchtrack.skeleton import Skeleton
    from torchtrack.synth.sequence import RigConfig, make_ring_rig
    from torchtrack.tracking.clearance import body_masks
    from torchtrack.tracking.search import search_near_in_images
    from torchtrack.tracking.voxels import ViewSilhouettes

    skel = Skeleton.from_urdf().scaled_to_height(1.75)
    blobs = BlobModel.from_config(skel)
    names, idx = list(skel.dof_names), [list(skel.output_names).index(n) for n in LANDMARKS]
    gen = torch.Generator().manual_seed(seed)
    truth = _walker(skel, gen)
    rig = make_ring_rig(RigConfig(num_cameras=8, width=320, height=240, radius_m=4.0)).float()
    fg = body_masks(rig, skel, truth[None], blobs=blobs)[0].float()  # (C, H, W)
    sil = ViewSilhouettes.from_evidence(2 * fg - 1, rig)
    valid = torch.zeros(8, dtype=torch.bool)
    valid[:] = cameras_shown == 8
    valid[[1, 2, 3]] = True
    predicted = truth.clone()
    for dof, off in {"root_tx": 0.1, "root_ty": -0.1, "root_rz": 0.15, "l_shoulder_flex": 0.25,
                     "r_knee_flex": -0.25}.items():
        predicted[names.index(dof)] += off * (1 if seed % 2 else -1)
    predicted = skel.clamp(predicted[None])[0]
    found = search_near_in_images(sil, valid, skel, blobs, predicted, torch.Generator().manual_seed(seed))

    def err(a):
        pts = skel.forward(torch.stack([a, truth]).double()).output_points[:, idx]
        return float((pts[0] - pts[1]).norm(dim=-1).mean())

    bound = 0.05 if cameras_shown == 8 else 0.09  # the cells are 4 px, 6 cm at 4 m
    assert err(found.angles) < bound and err(found.angles) < err(predicted) - 0.03, (err(found.angles),
                                                                                    err(predicted))
    assert found.cameras == cameras_shown and 0.5 < found.score <= 1.0, found


@pytest.mark.parametrize("case", [1, 2])
def test_a_stooped_body_is_found_where_the_images_score_it(case):
    """8 cameras: the search with the stooped prior lands within 60 mm of a stooped body's landmarks and at least
    80 mm nearer than without it (an upright pose meets the voxels only shrunk to their top; measured 41 / 20 mm
    with it against 160 / 171 without)."""
    from torchtrack.blobs import BlobModel
    from torchtrack.tracking.search import SearchConfig, search_pose

    from conftest import stooped_observation

    obs, skel, want, idx, _, _ = stooped_observation(case, 8)
    err = {}
    for stooped in (False, True):
        found = search_pose(obs, skel, BlobModel.from_config(skel), SearchConfig(stooped=stooped),
                            torch.Generator().manual_seed(0), n=1)
        body = skel.scaled_to_height(skel.height() * float(found.scale[0]))
        got = body.forward(found.angles[:1].double()).output_points[0, idx]
        err[stooped] = float((got - want).norm(dim=-1).mean())
    assert err[True] < 0.06 and err[True] < err[False] - 0.08, err


@pytest.mark.parametrize("cameras", [6, 7])
def test_the_stooped_prior_is_tried_from_7_cameras_only(cameras):
    """On 6 cameras (the images do not compare finished bodies there) the same hypotheses and the same answer with
    or without it; on 7, more hypotheses (the stooped poses and the folded elbows)."""
    from torchtrack.blobs import BlobModel
    from torchtrack.tracking.search import SearchConfig, search_pose

    from conftest import stooped_observation

    obs, skel, _, _, _, _ = stooped_observation(1, cameras)
    config = SearchConfig(layers=0)
    on, off = (search_pose(obs, skel, BlobModel.from_config(skel), dataclasses.replace(config, stooped=s),
                           torch.Generator().manual_seed(0), n=1) for s in (True, False))
    if cameras < 7:
        assert on.hypotheses == off.hypotheses
        torch.testing.assert_close(on.angles, off.angles, rtol=0, atol=0)
    else:
        assert on.hypotheses > off.hypotheses


@pytest.mark.parametrize("heading", [0.3, 2.2])
@pytest.mark.parametrize("cameras", [4, 6, 8])
def test_finished_bodies_on_a_few_views_hull_explain_their_own_ghosts_away(heading, cameras):
    """A few views' hull holds phantom volume, which a forearm folded into it before the chest explains as well as
    the hanging one explains the arm's own voxels. Compared on the voxels (below 7 cameras), each body's own ghosts
    (:func:`~torchtrack.tracking.ghosts.ghost_voxels`) leave the share it must explain: the true body then explains
    all of a hull carved from its own silhouettes (every voxel is the body or a ray-for-ray ghost of it), and the
    folded arm loses by more than on the plain voxels. From 7 cameras the images compare; the voxels' score there,
    where the observation has no images, stays the plain one."""
    from torchtrack.blobs import BlobModel
    from torchtrack.skeleton import Skeleton
    from torchtrack.tracking.search import score_states

    from conftest import carved_observation

    skel = Skeleton.from_urdf()
    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    names = list(skel.dof_names)
    truth = torch.zeros(skel.num_dofs, dtype=torch.float64)
    truth[names.index("root_rz")] = heading
    truth[names.index("l_shoulder_abd")] = truth[names.index("r_shoulder_abd")] = 0.15  # arms hanging
    truth[names.index("root_tz")] -= float(subj.forward(truth[None]).output_points[0, :, 2].min())
    folded = truth.clone()
    folded[names.index("r_shoulder_flex")], folded[names.index("r_elbow_flex")] = 0.3, 2.1
    obs = carved_observation(subj, blobs, truth, cameras)
    both = torch.stack([truth, folded])
    got = score_states(obs, subj, blobs, both)
    plain = score_states(dataclasses.replace(obs, camera_centres=None), subj, blobs, both)
    if cameras >= 7:
        for a, b in zip(got, plain):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
        return
    assert float(got[1][0]) > 0.999, got  # explained: all of the hull
    assert float(plain[1][0]) < 0.97, plain  # the phantom volume counted against it on the plain voxels
    margin, plain_margin = float(got[0][0] - got[0][1]), float(plain[0][0] - plain[0][1])
    assert margin > plain_margin + 0.005, (margin, plain_margin)
