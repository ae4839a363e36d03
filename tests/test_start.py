"""The start (torchtrack.tracking.start, torchtrack.tracking.search): the search from any pose, refusals, the
starfish fast path, on voxelised ground-truth bodies.
"""

from __future__ import annotations

import dataclasses
import math
import re

import pytest
import torch

from torchtrack.blobs import BlobModel
from torchtrack.checks import InputError
from torchtrack.conventions import LANDMARKS
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import procedural_motion
from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
from torchtrack.tracking.observation import VoxelObservation

from conftest import landmarks_of as _landmarks, voxelised_observation as _observation

torch.set_grad_enabled(False)


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


@pytest.mark.parametrize("frame, turn", [(12, 0.0), (20, 2.5), (5, -1.9)])
def test_the_search_starts_from_any_pose(skel, frame, turn):
    """The default start finds a subject 1.68 m tall mid-squat, arms forward, at any heading and off the centre,
    from the voxels of the true pose alone: landmarks within 50 mm of the truth (ground truth: the pose's forward
    kinematics)."""
    subj = skel.scaled_to_height(1.68)
    blobs = BlobModel.from_config(subj)
    truth = procedural_motion(subj, "squat", 1.0, 30, starfish_s=0.0)[frame].clone()
    names = list(skel.dof_names)
    truth[names.index("root_rz")] = turn
    truth[names.index("root_tx")] += 0.4
    truth[names.index("root_ty")] -= 0.3
    obs = _observation(subj, blobs, truth)
    tracker = MarkerlessTracker(skel)
    res = tracker.step(obs)
    assert res.valid and res.reinitialised
    want = subj.forward(truth[None].double()).output_points[0]
    err = (res.output_points.double() - want).norm(dim=-1).mean()
    assert float(err) < 0.05, float(err)
    assert abs(tracker.height_m - 1.68) < 0.1


def test_a_start_frame_with_two_people_is_refused_and_the_next_with_one_starts(skel):
    """Two people 1.5 m apart in the first frame (one squatting, one standing with the arms hanging): the start
    says so and the frame is invalid; the next frame, the squatting one alone, starts within 50 mm of the truth."""
    subj = skel.scaled_to_height(1.7)
    blobs = BlobModel.from_config(subj)
    crouch = procedural_motion(subj, "squat", 1.0, 30, starfish_s=0.0)[12].clone()
    alone = _observation(subj, blobs, crouch)
    other = _observation(skel.scaled_to_height(1.6), BlobModel.from_config(skel.scaled_to_height(1.6)),
                         skel.rest_angles(), shift=(0.0, 1.5, 0.0))
    both = VoxelObservation(*(torch.cat([a, b]) for a, b in zip(
        (alone.points, alone.sizes, alone.weights, alone.colours), (other.points, other.sizes, other.weights,
                                                                    other.colours))), alone.cameras_valid)
    tracker = MarkerlessTracker(skel)
    first = tracker.step(both)
    assert not first.valid and not tracker.initialized
    assert len(tracker.start_refusals) == 1
    assert re.search(r"2 separate person-sized parts .*--init-pose", tracker.start_refusals[0]), \
        tracker.start_refusals[0]
    res = tracker.step(alone)
    assert res.valid and res.reinitialised
    want = subj.forward(crouch[None].double()).output_points[0]
    assert float((res.output_points.double() - want).norm(dim=-1).mean()) < 0.05


def test_a_start_frame_with_the_body_half_out_of_the_volume_is_refused(skel):
    """A standing body whose left half lies out of the observed box (only its voxels inside kept): the search's
    start refuses it, naming the capture volume, rather than starting on the half it sees."""
    subj = skel.scaled_to_height(1.7)
    blobs = BlobModel.from_config(subj)
    obs = _observation(subj, blobs, subj.rest_angles())
    inside = obs.points[:, 1] < 0.0  # the body faces +x: its left side is +y
    box = ((-2.0, -2.0, 0.0), (2.0, 0.0, 2.5))
    half = VoxelObservation(obs.points[inside], obs.sizes[inside], obs.weights[inside], obs.colours[inside],
                            obs.cameras_valid, volume_m=box)
    tracker = MarkerlessTracker(skel)
    with pytest.raises(InputError, match=r"lies out of the capture volume"):
        tracker.initialize(half)
    assert not tracker.initialized


def test_the_search_finds_a_real_pose_no_product_of_limb_poses_gives(skel):
    """A pose of a real capture far from every pose of the structured prior (a crouch with the trunk twisted),
    perturbed and at another heading and size: the search alone (no EM/IK) ends within 60 mm of it (ground truth:
    the pose's forward kinematics)."""
    from torchtrack.tracking.poses import pose_prior, real_pose_prior
    from torchtrack.tracking.search import SearchConfig, search_pose

    real, structured = real_pose_prior(skel), pose_prior(skel)
    idx = [list(skel.output_names).index(n) for n in LANDMARKS]

    def shape(a):
        p = skel.forward(a).output_points[:, idx]
        return p - p[:, :1]

    gap = torch.cdist(shape(real).flatten(1), shape(structured).flatten(1)).amin(1)  # to the nearest structured
    gen = torch.Generator().manual_seed(5)
    truth = real[int(gap.argmax())].clone()
    truth[6:] = skel.clamp(truth + 0.08 * torch.randn(truth.shape, generator=gen, dtype=truth.dtype))[6:]
    names = list(skel.dof_names)
    subj = skel.scaled_to_height(1.62)
    truth[names.index("root_rz")] = 2.2
    truth[names.index("root_tx")] = 0.3
    fk = subj.forward(truth[None].double())
    truth[names.index("root_tz")] -= float(fk.output_points[0, :, 2].min())  # the soles on the floor
    blobs = BlobModel.from_config(subj)
    obs = _observation(subj, blobs, truth)
    template_blobs = BlobModel.from_config(skel)
    found = search_pose(obs, skel, template_blobs, SearchConfig(real_poses=True), torch.Generator().manual_seed(0),
                        n=1)
    body = skel.scaled_to_height(skel.height() * float(found.scale[0]))
    got = body.forward(found.angles[:1].double()).output_points[0]
    want = subj.forward(truth[None].double()).output_points[0]
    err = float((got - want).norm(dim=-1).mean())
    assert err < 0.06, err


@pytest.mark.parametrize("case", [1, 2])
def test_the_limb_sweep_on_the_fitted_body_finds_an_arm_the_start_left_off(skel, case):
    """8 cameras, a body stooped with a hand at the chest, fitted with that arm hanging (the body's own proportions,
    EM/IK from there): sweeping the finished start's limbs again puts the landmarks within 20 mm of the truth (ground
    truth: the pose's forward kinematics), 25 mm nearer than the fit (measured 41 / 49 -> 9 / 8 mm); a fit from the
    true pose stays within 2 mm of where it was."""
    from conftest import stooped_observation

    obs, _, want, idx, truth, subj = stooped_observation(case, 8)
    names = list(skel.dof_names)
    hanging = truth.clone()
    for dof, value in {"r_shoulder_flex": 0.0, "r_shoulder_abd": 0.1, "r_elbow_flex": 0.1}.items():
        hanging[names.index(dof)] = value
    err = {}
    for start in ("hanging", "truth"):
        tracker = MarkerlessTracker(skel, TrackerConfig())
        tracker.initialize_from_pose((hanging if start == "hanging" else truth).float(), skeleton=subj)
        for _ in range(4):  # the start's fit
            res = tracker._track(obs, learn_colour=False, max_rot=math.radians(45))
            tracker.angles = tracker.previous = res.angles
        swept = tracker._sweep_finished_limbs(obs, res)
        err[start] = [float((r.output_points[idx] - want).norm(dim=-1).mean()) for r in (res, swept)]
    (fit, swept), (right, kept) = err["hanging"], err["truth"]
    assert swept < 0.02 and swept < fit - 0.025 and kept < right + 0.002, err


@pytest.mark.parametrize("arm", [0.95, 1.75, 2.2])
def test_starfish_arms_measured_from_the_voxels(skel, arm):
    """The starfish start reads the arms' abduction from the voxels' far ends (the hands, seen from the shoulders of
    the body scaled to the voxels): within 0.05 rad of the truth for arms below, above and far above the
    shoulders (a voxelised starfish turned 0.7 rad), and the start lands within 20 mm."""
    subj = skel.scaled_to_height(1.7)
    truth = subj.starfish_angles(arm_abduction=arm)
    truth[skel.dof_names.index("root_rz")] = 0.7
    obs = _observation(subj, BlobModel.from_config(subj), truth)
    tracker = MarkerlessTracker(skel, TrackerConfig(start="starfish"))
    tracker._setup(1.7, obs.points.device)
    p, w = obs.points, obs.weights
    centre = (w[:, None] * p).sum(0) / w.sum()
    lateral = torch.tensor([-math.sin(0.7), math.cos(0.7)])  # the arms' line
    measured = tracker._starfish_arm_abduction(p, w, (p[:, :2] - centre[:2]) @ lateral, float(p[:, 2].min()))
    assert abs(measured - arm) < 0.05, measured
    res = tracker.initialize(obs)
    err = float((res.output_points[:16].double() - _landmarks(subj, truth).double()).norm(dim=-1).mean())
    assert err < 0.02, err


@pytest.mark.parametrize("starfish", [True, False])
def test_a_starfish_start_takes_the_fast_path_where_the_search_misses(skel, monkeypatch, starfish):
    """The search's answer forced wrong (its arms hanging): on a starfish frame the starfish's fast path starts
    within 30 mm of the truth instead (ground truth: the pose's forward kinematics); on a frame of someone standing
    with the arms down the fast path refuses it, and the search's answer is kept."""
    import torchtrack.tracking.search as search

    names = list(skel.dof_names)
    arms = [i for i, n in enumerate(names) if "shoulder" in n or "elbow" in n]
    found = search.search_pose

    def hanging(obs, sk, *a, **k):
        r = found(obs, sk, *a, **k)
        angles = r.angles.clone()
        angles[:, arms] = sk.rest_angles().to(angles)[arms]
        return dataclasses.replace(r, angles=angles)

    monkeypatch.setattr(search, "search_pose", hanging)
    subj = skel.scaled_to_height(1.7)
    truth = subj.starfish_angles() if starfish else subj.rest_angles()
    truth[names.index("root_rz")] = 0.7
    truth[names.index("root_tx")] += 0.3
    tracker = MarkerlessTracker(skel, TrackerConfig(start_race_s=0.0))
    res = tracker.step(_observation(subj, BlobModel.from_config(subj), truth))
    assert res.valid and res.reinitialised
    err = float((res.output_points[:16].double() - _landmarks(subj, truth).double()).norm(dim=-1).mean())
    if starfish:
        assert err < 0.03, err
    else:  # the search's (forced) answer: the arms hang as the truth's do
        assert err < 0.05, err
    # the starfish's start measures how far its toes point ahead; the search's leaves it NaN
    assert math.isnan(tracker.start_check.toe_ahead_m) != starfish


def test_a_standing_start_beside_a_phantom_is_no_starfish(skel):
    """Arms hanging, a person-high phantom column 0.6 m to the side (as a static ghost in an estimated background):
    the voxels span as wide as a starfish, but the arms are not where the starfish puts them."""
    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    obs = _observation(subj, blobs, subj.rest_angles())
    g = torch.arange(0.015, 0.15, 0.03)
    col = torch.stack(torch.meshgrid(g - 0.075, g + 0.6, torch.arange(0.615, 1.5, 0.03), indexing="ij"), -1)
    col = col.reshape(-1, 3).float()
    n = col.shape[0]
    obs = VoxelObservation(torch.cat([obs.points, col]), torch.cat([obs.sizes, obs.sizes[:n]]),
                           torch.cat([obs.weights, obs.weights[:n]]),
                           torch.cat([obs.colours, obs.colours[:1].expand(n, -1, -1)]), obs.cameras_valid)
    tracker = MarkerlessTracker(skel, TrackerConfig(start="starfish"))
    with pytest.raises(InputError, match=r"the (left|right|left and right) arms? (is|are) not raised.*--init-pose"):
        tracker.initialize(obs)
    assert not tracker.initialized


@pytest.mark.parametrize("contact", [False, True])
def test_a_starfish_inside_phantom_volume_is_refused(skel, contact):
    """A voxelised starfish (0.057 m^3 of body) and a 0.6 m phantom box (0.22 m^3) behind it: the voxels hold
    about 5 times the volume of a body as tall as they are, which is not one person, however the fit (which may
    grow the body into the box) goes."""
    subj = skel.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    obs = _observation(subj, blobs, subj.starfish_angles())
    g = torch.arange(0.015, 0.6, 0.03)
    box = torch.stack(torch.meshgrid(g - 0.9, g - 0.3, g + 0.3, indexing="ij"), -1).reshape(-1, 3).float()
    n = box.shape[0]
    size = obs.sizes[:1].expand(n)
    colours = torch.cat([obs.colours, obs.colours[:1].expand(n, -1, -1)])
    obs = VoxelObservation(torch.cat([obs.points, box]), torch.cat([obs.sizes, size]),
                           torch.cat([obs.weights, size ** 3]), colours, obs.cameras_valid)
    body_m3 = float((4 / 3 * math.pi * blobs.semi_axes.double().prod(-1)).sum())  # the 1.75 m body's blobs
    tracker = MarkerlessTracker(skel, TrackerConfig(floor_contact=contact, start="starfish"))
    with pytest.raises(InputError, match=r"times the volume of a body as tall as they are.*--init-pose") as err:
        tracker.initialize(obs)
    found = re.search(r"hold ([0-9.]+) times .* \(([0-9.]+) m;", str(err.value))
    ratio, height = float(found.group(1)), float(found.group(2))
    assert abs(height - 1.75) < 0.12  # the voxels' quantiles: the box's many voxels dilute the head's top
    assert ratio == pytest.approx(obs.volume_m3() / (body_m3 * (height / 1.75) ** 3), abs=0.06)
    assert ratio > 4.0
    assert tracker.start_check.volume_ratio == pytest.approx(ratio, abs=0.05)  # the measures stay readable
    assert not tracker.initialized
    if not contact:  # the search's start refuses it too (with floor contact it is taken: a known gap)
        searching = MarkerlessTracker(skel, TrackerConfig(floor_contact=contact))
        with pytest.raises(InputError, match=r"times the volume of a body|does not fit a person"):
            searching.initialize(obs)


@pytest.mark.parametrize("flip_better_mm, flipped", [(1.0, False), (3.0, True)])
def test_starfish_heading_the_toes_point_along_wins_a_near_tie(skel, monkeypatch, flip_better_mm, flipped):
    """Toes 1 cm ahead of the body's centre (under the 3 cm that settles the heading alone): the start tries the
    toes' heading and its flip, and keeps the toes' unless the flip fits better by more than HEADING_MARGIN_M
    (2 mm). The fit's cost is replaced by one that favours the flip by ``flip_better_mm``."""
    from torchtrack.tracking import markerless

    subj = skel.scaled_to_height(1.75)
    obs = _observation(subj, BlobModel.from_config(subj), subj.starfish_angles())  # facing +X, heading 0
    p, w = obs.points.double(), obs.weights.double()
    low = p[:, 2] < p[:, 2].min() + 0.08 * 1.75
    wl = float(w[low].sum() / w.sum())
    ahead = float((w[low] * p[low, 0]).sum() / w[low].sum() - (w * p[:, 0]).sum() / w.sum())
    assert ahead > 0.03  # the template's feet: the toes alone would settle it
    shift = (0.01 - ahead) / (1.0 - wl)  # move the feet back until they are 1 cm ahead of the new centre
    pts = p.clone()
    pts[low, 0] += shift
    obs = dataclasses.replace(obs, points=pts.float())
    rz = skel.dof_names.index("root_rz")
    headings = []

    def cost(res):
        heading = float(res.angles[rz])
        headings.append(heading)
        back = math.cos(heading) < 0  # the flip of the +X facing
        return 0.02 - (flip_better_mm * 1e-3 if back else 0.0)

    monkeypatch.setattr(markerless.MarkerlessTracker, "_fit_cost", staticmethod(cost))
    tracker = MarkerlessTracker(skel, TrackerConfig(fit_bone_lengths=False, start="starfish"))
    res = tracker.step(obs)
    assert markerless.HEADING_MARGIN_M == pytest.approx(0.002)
    assert len(headings) >= 2 and math.cos(headings[0]) > 0.9 and math.cos(headings[1]) < -0.9  # toes', flip
    assert (math.cos(float(res.angles[rz])) < 0) == flipped
    # what the start reports: the toes 1 cm ahead, the two headings tried with their costs
    check = tracker.start_check
    assert check.toe_ahead_m == pytest.approx(0.01, abs=3e-3)
    assert [c for _, c in check.headings[:2]] == pytest.approx([0.02, 0.02 - flip_better_mm * 1e-3])
    assert math.cos(check.headings[0][0]) > 0.99 and math.cos(check.headings[1][0]) < -0.99  # toes', flip


def test_a_start_too_tall_is_rescaled_until_the_fitted_pose_spans_the_voxels(skel):
    """A standing subject 1.66 m tall, started as a 1.80 m body at the true pose (the root's height scaled with
    it): the size check rescales the body until the fitted pose spans the voxels' height, which lands it within
    3 cm of the truth (ground truth: the subject's own height; without the check it stays at 1.80)."""
    names = list(skel.dof_names)
    subj = skel.scaled_to_height(1.66)
    truth = subj.rest_angles()
    truth[names.index("l_shoulder_abd")] = truth[names.index("r_shoulder_abd")] = 0.4  # arms off the trunk
    truth[names.index("root_tz")] -= float(subj.forward(truth[None]).output_points[0, :, 2].min())  # on the floor
    obs = _observation(subj, BlobModel.from_config(subj), truth)
    tracker = MarkerlessTracker(skel, TrackerConfig())
    start = truth.clone()
    start[names.index("root_tz")] *= 1.80 / 1.66
    tracker.initialize_from_pose(start.float(), 1.80)
    res = tracker._track(obs, learn_colour=False, max_rot=math.radians(45))
    tracker.angles = tracker.previous = res.angles
    sole, top = obs.height_span()
    assert tracker._span(res.angles) > (top - sole) + 0.02  # too tall: the fitted pose overshoots the voxels
    res = tracker._fit_size_to_span(obs, res)
    assert abs(tracker.height_m - 1.66) < 0.03, tracker.height_m
    assert abs(tracker._span(res.angles) - (top - sole)) < 0.02
