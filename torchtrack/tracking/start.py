"""The tracker's automatic start (:class:`~torchtrack.tracking.markerless.MarkerlessTracker`'s part that finds the
first pose): the search from any pose (:mod:`torchtrack.tracking.search`) finished by EM/IK, the starfish start
(Caillette §4.2) with its checks, and the subject's size and bones fitted to the first frame; the start race that
follows is :mod:`torchtrack.tracking.race`.
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch

from torchtrack.blobs.model import BlobModel, blob_volumes
from torchtrack.checks import InputError
from torchtrack.conventions import LANDMARKS
from torchtrack.tracking.voxels import VoxelObservation
from torchtrack.tracking.bone_fit import BONE_FIT_VOXEL_M, FIT_ROUNDS
from torchtrack.tracking.goals import sole_heights
from torchtrack.tracking.race import START_RACE_MARGIN
from torchtrack.tracking.step import FrameResult

if TYPE_CHECKING:
    from torchtrack.tracking.markerless import MarkerlessTracker

log = logging.getLogger(__name__)

#: The search's start is refused where more of the body than this lies out of the observed volume.
START_MAX_OUTSIDE = 0.2
#: A start frame whose voxels hold two separate people is refused (torchtrack tracks one person). A connected part
#: of the voxels (:meth:`VoxelObservation.parts`) is a person when it is at least PERSON_MIN_HEIGHT_M tall (a deep
#: squat still is) and holds at least PERSON_MIN_VOLUME of the smallest body the search looks for: floor shadows,
#: a foot's stray voxels and a phantom column of an estimated background are lower or smaller.
PERSON_MIN_HEIGHT_M = 1.0
PERSON_MIN_VOLUME = 0.5
#: Initialisation: the heading the toes point along (the first tried) gives way to another only if that fits the
#: starfish frame better by more than this (m of the fit's cost, :meth:`MarkerlessTracker._fit_cost`). Where the
#: toes are unclear the fits of a starfish and of its flip are often a tie, and a flip that wins by noise tracks the
#: whole sequence backwards (docs/results.md, "Tracker settings").
HEADING_MARGIN_M = 0.002
#: A starfish's arms are raised: the initialisation refuses a fit whose upper arm hangs within this angle of
#: straight down (the starfish pose has them 72 deg up; the synthetic starts' fits stay well above this:
#: docs/results.md, "Tracker settings").
STARFISH_MIN_ARM_RAISE_DEG = 45.0
#: The starfish start tries the template's arms (``Skeleton.starfish_angles``' abduction, rad from hanging) and,
#: where it differs from them by more than ``STARFISH_ARM_MARGIN``, the abduction the voxels' far ends show (their
#: outermost ``STARFISH_HAND_SHARE`` along the arms' line: the hands): starfish are held with the arms anywhere
#: from below to above the shoulders, and a fit from the template's may not reach an arm held far from it.
STARFISH_ARM_ABDUCTION = 1.25
STARFISH_ARM_MARGIN = 0.2
STARFISH_HAND_SHARE = 0.02
#: The starfish frame's voxels may hold at most this many times the volume of the body (its blobs' ellipsoids)
#: scaled to their height: more is not one person (phantom volume; a background estimated from a video whose
#: subject stands still, painted out with the room around them). The synthetic starts stay well under it and the
#: Pose2Sim demo's first frame on the filled background well over it (docs/results.md, "Tracker settings").
STARFISH_MAX_VOLUME_RATIO = 3.0
#: The start's size is a guess of the pose it assumes (the voxels' height over the starfish's top-to-standing ratio
#: of the template's style, or the search's scale of its prior pose); the fitted pose measures it: the body is
#: rescaled, at most this many rounds each followed by EM/IK passes, until the fitted pose spans the voxels' height
#: (lowest sole to highest point) within SPAN_TOLERANCE. A starfish of another style or a search's pose crouched
#: into a fat few-camera hull otherwise starts the body several cm too tall, its feet under the floor
#: (docs/results.md, "Robustness", the 4-camera rows).
SPAN_ROUNDS = 3
SPAN_TOLERANCE = 0.005
#: ... and within this fraction of the guess (the blob-scale fit's bound, below): the pose's guess is off by a few
#: per cent, more is a frame the fit does not explain (phantom volume, a second body), which the checks refuse.
SPAN_MAX_CHANGE = 0.1
#: What every refusal of the automatic initialisation tells the user to do.
START_ADVICE = ("The tracker starts at the first frame that shows one whole person in the capture volume; with the "
                "starfish start (tracker start: starfish), in the starfish pose. Or give an initial pose with "
                "--init-pose START.npz: a poses.npz of this subject whose first valid frame is the pose (an earlier "
                "run's output), or one fitted to 3D keypoints of the first frame by `torchtrack init-pose "
                "KEYPOINTS.trc --out START.npz`")


@dataclass(frozen=True)
class StartCheck:
    """What the automatic initialisation measured of its starfish fit (accepted or refused).

    Attributes:
        height_m: the subject's height from the voxels. volume_ratio: the voxels' volume over that of the body
            (its blobs' ellipsoids) at that height (``STARFISH_MAX_VOLUME_RATIO``).
        arm_raise_deg: (left, right) each fitted upper arm's angle from hanging straight down
            (``STARFISH_MIN_ARM_RAISE_DEG``). arm_fill: (left, right) the larger fill of each arm's upper-arm and
            forearm blobs (NaN for a blob config without them; ``em.min_fill``).
        toe_ahead_m: how far the lowest voxels' centroid lies ahead of all the voxels' along the heading the toes
            point to (>= 0; 3 cm or more settles the heading alone).
        headings: (heading about +Z in rad, the fit's cost in m) of each heading tried, in the order tried (the
            toes' first; ``HEADING_MARGIN_M``).
    """

    height_m: float
    volume_ratio: float
    arm_raise_deg: tuple[float, float]
    arm_fill: tuple[float, float]
    toe_ahead_m: float = math.nan
    headings: tuple[tuple[float, float], ...] = ()


class StartMixin:
    """The start's methods of :class:`~torchtrack.tracking.markerless.MarkerlessTracker` (its state: see there)."""

    def _starfish_top_ratio(self) -> float:
        """Head-top height in the starfish pose over standing height (the spread legs lower the body)."""
        g = self.generic
        top = g.forward_frames(g.starfish_angles()[None])[0, g.frame_index(["head_top"])[0], 2, 3]
        return float(top) / g.height()

    def initialize(self, obs: VoxelObservation) -> FrameResult:
        """Automatic initialisation from a starfish frame (see the module docstring).

        Raises:
            InputError: the voxels do not look like a person in the starfish pose (the tracker is then left
            uninitialised, as before the call).
        """
        self.feet_seen = self.feet_still = None  # nothing held while the start is searched
        self.hands_off = [0, 0]
        try:
            res = self._initialize(obs)
        except InputError:
            self._clear()
            raise
        self._remember_feet()
        self._start_hips(learn=True)
        if self.config.start == "search" and self.config.start_race_s > 0:
            self._start_race(obs, res, self._unswept)
        return res

    def _fork(self) -> MarkerlessTracker:
        """A copy of this tracker's state that tracks on its own (the models and settings shared, read-only)."""
        shared = (self.generic, self.config, self.blob_specs, self.subject)
        # the frames kept to track back, and the invalid ones kept to hold back (image_hold_s), stay with this tracker
        settle, unheld, self._settle, self._unheld = self._settle, self._unheld, None, []
        try:
            return copy.deepcopy(self, memo={id(x): x for x in shared})
        finally:
            self._settle, self._unheld = settle, unheld

    def _initialize(self, obs: VoxelObservation) -> FrameResult:
        self.girth = 1.0  # the template's until the start's fit measures it
        if obs.num_observed < self.config.min_voxels or obs.volume_m3() < self.config.min_volume_m3:
            raise InputError("initialisation: the first frame has nobody in the tracking volume")
        self.check_one_person(obs)
        if self.config.start == "starfish":
            res, height, body_m3, toe, tried = self._starfish_fit(obs)
            return self._finish_start(obs, res, height, body_m3, toe, tried)
        before = self._fork()  # the state before the start, for the starfish's fast path
        res, height, body_m3, tried = self._search_fit(obs)
        res = self._finish_start(obs, res, height, body_m3, math.nan, tried)
        return self._starfish_fast_path(obs, res, before)

    def _starfish_fast_path(self, obs: VoxelObservation, res: FrameResult, before: MarkerlessTracker
                            ) -> FrameResult:
        """A searched start (``res``, this tracker's state) against the starfish start from the same state
        (``before``), where its checks take the frame for a starfish: the starfish's is kept unless the searched
        one's finished pose scores higher on ``obs`` by more than ``START_RACE_MARGIN`` (the search's two-way score,
        each with its own fitted body). The starfish's placement (arms' line, toes, the voxels' height) lands where
        the search's sampled poses may not, e.g. arms raised above the shoulders on a body of unusual proportions;
        and a starfish scores the same turned round, which its toes tell and the score does not (docs/results.md,
        "The start search")."""
        from torchtrack.tracking.search import score_states

        starfish = before
        starfish.config = replace(self.config, start="starfish")
        try:
            fit, height, body_m3, toe, tried = starfish._starfish_fit(obs)
            alt = starfish._finish_start(obs, fit, height, body_m3, toe, tried)
        except InputError as exc:  # not a starfish: the search's start stays
            log.debug("start: the starfish's fast path does not take the frame (%s)", str(exc).split(". ")[0])
            return res
        own, other = (float(score_states(obs, t.subject.skeleton, t.subject.blobs, r.angles[None])[0][0])
                      for t, r in ((self, res), (starfish, alt)))
        log.debug("start: the search's start scores %.3f, the starfish's %.3f", own, other)
        if other < own - START_RACE_MARGIN:
            return res
        config = self.config
        self.__dict__.update(starfish.__dict__)  # this tracker goes on from the starfish's start
        self.config = config
        return alt

    def _body_volume_range(self, device: torch.device) -> tuple[float, float]:
        """The volume (m^3) of the template's blobs at the smallest and the largest size the start's search looks
        for (the default :class:`~torchtrack.tracking.search.SearchConfig`'s, which the start uses)."""
        from torchtrack.tracking.search import SearchConfig

        self.generic.to(device)
        body = float(blob_volumes(BlobModel(self.generic, *self.blob_specs)).sum())
        lo, hi = SearchConfig().scale_range
        return lo ** 3 * body, hi ** 3 * body

    def check_one_person(self, obs: VoxelObservation) -> None:
        """Refuse a start frame with two or more separate people in it (:data:`PERSON_MIN_HEIGHT_M`)."""
        _, volume, span = obs.parts()
        person = (span[:, 1] - span[:, 0] >= PERSON_MIN_HEIGHT_M) & (
            volume >= PERSON_MIN_VOLUME * self._body_volume_range(obs.points.device)[0])
        if int(person.sum()) > 1:
            vols = ", ".join(f"{float(v):.3f}" for v in volume[person])
            raise InputError(f"initialisation: the frame's voxels form {int(person.sum())} separate person-sized "
                             f"parts ({vols} m^3, each at least {PERSON_MIN_HEIGHT_M:g} m tall): two people, or a "
                             "person and an object the background does not hold; the tracker follows one person. "
                             + START_ADVICE)

    def _sole(self, obs: VoxelObservation) -> float:
        """The soles' height: the lowest voxels' bottom (:meth:`VoxelObservation.height_span`)."""
        return obs.height_span()[0]

    def _search_fit(self, obs: VoxelObservation) -> tuple[FrameResult, float, float, tuple]:
        """The search's best hypotheses (:func:`~torchtrack.tracking.search.search_pose`), each finished by
        ``init_passes`` EM/IK passes; the least :meth:`_fit_cost` wins. Returns the fit, the subject's height,
        the body's volume and ``(hypothesis, cost)`` of each tried."""
        from torchtrack.tracking.search import SearchConfig, score_states, search_pose

        dev = obs.points.device
        largest = self._body_volume_range(dev)[1]
        blobs = BlobModel(self.generic, *self.blob_specs)
        if obs.volume_m3() > STARFISH_MAX_VOLUME_RATIO * largest:  # checked before the search: a refusal is cheap
            raise InputError(f"initialisation: the frame's voxels hold {obs.volume_m3() / largest:.1f} times the "
                             "volume of the largest body searched for: not one person (phantom volume, or a "
                             "background that keeps parts of the room). " + START_ADVICE)
        gen = torch.Generator(device=dev).manual_seed(self.config.search_seed)
        found = search_pose(obs, self.generic, blobs, SearchConfig(real_poses=self.config.start_real_poses,
                                                                prior_exclude=self.config.start_prior_exclude),
                            gen, n=self.config.start_hypotheses)
        if float(found.outside[0]) > START_MAX_OUTSIDE:
            raise InputError(f"initialisation: {100 * float(found.outside[0]):.0f}% of the body found lies out of "
                             "the capture volume: not started on a body partly out of it")
        height = self.generic.height() * float(found.scale[0])
        self._setup(height, dev)
        self._set_floor(self._sole(obs))
        fits, tried = [], []
        for k in range(found.angles.shape[0]):
            self.angles = self.previous = found.angles[k].to(obs.points.dtype)
            self.colour, self.lost = None, 0
            res = None
            for _ in range(self.config.init_passes):
                res = self._track(obs, learn_colour=False, max_rot=math.radians(45), predicted=False)
                self.angles = self.previous = res.angles
            fits.append(res)
        # the finished hypotheses compared as the search compares them (EM/IK's own cost cannot tell a body turned
        # front to back from the right one: both fit the voxels' blobs)
        angles = torch.stack([r.angles for r in fits])
        score = score_states(obs, self.subject.skeleton, self.subject.blobs, angles)[0]
        for k, res in enumerate(fits):
            tried.append((float(k), float(score[k])))
            log.debug("start search: hypothesis %d (search score %.3f): score %.3f after EM/IK, residual %.1f mm, "
                      "explained %.2f", k, float(found.score[k]), float(score[k]), 1e3 * res.residual_m,
                      res.explained)
        res = fits[int(score.argmax())]
        self.angles = self.previous = res.angles
        return res, height, self.subject.body_volume_m3, tuple(tried)

    def _starfish_fit(self, obs: VoxelObservation) -> tuple[FrameResult, float, float, float, tuple]:
        """The starfish start's fit (Caillette §4.2, module docstring). Returns the fit, the subject's height, the
        body's volume, how far the toes point ahead and ``(heading, cost)`` of each heading tried."""
        pts, w = obs.points, obs.weights
        # the soles may stand above z = 0 (a platform, a calibration with the floor lower): measure from them
        sole, top = obs.height_span()
        height = min(max((top - sole) / self._starfish_top_ratio(), 0.5), 2.5)
        self._setup(height, pts.device)
        body_m3 = self.subject.body_volume_m3
        self._set_floor(sole)
        skel = self.subject.skeleton
        c = (w[:, None] * pts).sum(0) / w.sum()
        d = pts[:, :2] - c[:2]
        cov = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) / w.sum()
        evals, evecs = torch.linalg.eigh(cov)
        lateral = evecs[:, 1]  # the arms and legs spread left-right
        facing = torch.stack([lateral[1], -lateral[0]])
        low = pts[:, 2] < sole + 0.08 * height
        feet = (w[low, None] * d[low]).sum(0) / w[low].sum() if bool(low.any()) else d.new_zeros(2)
        if float(feet @ facing) < 0:
            facing = -facing
        along = d @ lateral
        span = float(torch.quantile(along, 0.995) - torch.quantile(along, 0.005))
        if span < 0.5 * height:  # a starfish spans about 0.9 of the height hand to hand, a standing body 0.3
            raise InputError(
                f"initialisation: the first frame with a person does not look like the starfish pose (arm span "
                f"{span:.2f} m for a height of {height:.2f} m). " + START_ADVICE)
        yaw = math.atan2(float(facing[1]), float(facing[0]))
        best = None
        # the horizontal spread's main axis is the arms' line and the toes tell front from back (they point
        # 5-8 cm ahead of the body's centre); the fit decides only what these leave open (it cannot tell a
        # flipped starfish from the right one reliably, as the hull's ghosts fit either)
        toe = float(feet @ facing)  # >= 0 by the choice of facing
        candidates = [yaw] if toe > 0.03 else [yaw, yaw + math.pi]
        if float(evals[1]) < 1.3 * float(evals[0]):  # no clear arms' line: try the quarter turns as well
            candidates += [h + 0.5 * math.pi for h in candidates]
        # the arms as raised as the voxels' far ends show, where that differs from the template's starfish
        arms = [STARFISH_ARM_ABDUCTION]
        measured = self._starfish_arm_abduction(pts, w, along, sole)
        if abs(measured - STARFISH_ARM_ABDUCTION) > STARFISH_ARM_MARGIN:
            arms.append(measured)
        tried = []  # (heading, cost) of each candidate
        for candidate, arm in ((c, arm) for c in candidates for arm in arms):
            a = skel.starfish_angles(arm_abduction=arm).to(pts)
            a[skel.dof_names.index("root_tz")] += max(sole, 0.0)
            a[skel.dof_names.index("root_tx")] = c[0]
            a[skel.dof_names.index("root_ty")] = c[1]
            a[skel.dof_names.index("root_rz")] = candidate
            self.angles = self.previous = a
            self.colour, self.lost = None, 0
            res = None
            for _ in range(self.config.init_passes):
                res = self._track(obs, learn_colour=False, max_rot=math.radians(45), predicted=False)
                self.angles = self.previous = res.angles
            cost = self._fit_cost(res)
            tried.append((float(candidate), float(cost)))
            log.debug("initialisation: heading %.2f rad: residual %.1f mm, explained %.2f", candidate,
                      1e3 * res.residual_m, res.explained)
            # the toes' heading (the first) is kept unless another fits clearly better
            margin = HEADING_MARGIN_M if best is not None and best[2] and candidate != candidates[0] else 0.0
            if best is None or cost < best[0] - margin:
                best = (cost, res, candidate == candidates[0] and toe > 0.0)
        res = best[1]
        self.angles = self.previous = res.angles
        return res, height, body_m3, toe, tuple(tried)

    def _starfish_arm_abduction(self, pts: torch.Tensor, w: torch.Tensor, along: torch.Tensor, sole: float) -> float:
        """The arms' abduction (rad from hanging, both sides' mean) that puts the hands where the voxels' far ends
        along the arms' line lie (their outermost ``STARFISH_HAND_SHARE``), seen from the shoulders of the body
        scaled to the voxels (:attr:`subject`)."""
        skel = self.subject.skeleton
        lm = skel.forward(skel.starfish_angles()[None].to(skel.lower)).landmarks[0]  # facing +X, soles at z = 0
        shoulder = lm[LANDMARKS.index("l_shoulder")]
        reach, drop = [], []
        for side in (1.0, -1.0):
            x = side * along
            far = x >= torch.quantile(x, 1.0 - STARFISH_HAND_SHARE)
            wf = w[far] / w[far].sum()
            reach.append(float((wf * x[far]).sum()) - abs(float(shoulder[1])))
            drop.append(float(shoulder[2]) - (float((wf * pts[far, 2]).sum()) - sole))
        angle = sum(math.atan2(r, d) for r, d in zip(reach, drop)) / 2
        return min(max(angle, 0.0), math.pi)

    def _span(self, angles: torch.Tensor) -> float:
        """The body's height span at ``angles (D,)``: its highest output point (head top, hand tips) over its lowest
        sole or point (m)."""
        sub = self.subject
        fk = sub.skeleton.forward(angles[None])
        points = fk.output_points[0]
        low = torch.minimum(sole_heights(fk.joints[0, sub.feet], sub.ankle_height).min(), points[:, 2].min())
        return float(points[:, 2].max() - low)

    def _refit(self, obs: VoxelObservation) -> FrameResult:
        """The EM/IK passes that follow each change of the start's body (its size, girth or bones): ``max(2,
        init_passes // 3)`` of them from the tracker's state, which follows each; the last pass's fit."""
        for _ in range(max(2, self.config.init_passes // 3)):
            res = self._track(obs, learn_colour=False, max_rot=math.radians(45))
            self.angles = self.previous = res.angles
        return res

    def _fit_size_to_span(self, obs: VoxelObservation, res: FrameResult) -> FrameResult:
        """The body rescaled until the fitted pose spans the voxels' height (``SPAN_ROUNDS``), the root's height
        above the soles scaled with it, each round finished by EM/IK passes."""
        sole, top = obs.height_span()
        iz = self.subject.skeleton.dof_names.index("root_tz")
        guess = self.height_m
        for _ in range(SPAN_ROUNDS):
            span = self._span(res.angles)
            s = (top - sole) / span
            if not math.isfinite(s):
                break
            # a correction of the pose's guess, not a new guess: within SPAN_MAX_CHANGE of it (a phantom's voxels
            # must not grow the body without bound)
            lo, hi = (1 - SPAN_MAX_CHANGE) * guess, (1 + SPAN_MAX_CHANGE) * guess
            s = min(max(s * self.height_m, lo), hi) / self.height_m
            if abs(s - 1.0) < SPAN_TOLERANCE:
                break
            log.debug("start: the fitted pose spans %.3f m, the voxels %.3f m: the body rescaled by %.3f",
                      span, top - sole, s)
            angles = res.angles.clone()
            angles[iz] = sole + (angles[iz] - sole) * s
            self._setup(self.height_m * s, angles.device)
            self.angles = self.previous = angles
            res = self._refit(obs)
        return res

    def _finish_start(self, obs: VoxelObservation, res: FrameResult, height: float, body_m3: float, toe: float,
                      tried: tuple) -> FrameResult:
        """From a start's fit: the bone fit, the checks (the starfish's raised arms only for its start), the
        colours learnt. The pose was chosen on every voxel (a floor shadow's ghost may lie in the floor band, but so
        do the toes, which tell the body's front from its back); the fit and the body from here on without the
        floor band's (``floor_band_m``)."""
        obs = self._without_floor_band(obs)
        pts = obs.points
        # the bone fit's rounds explain ghosts away: so does the fit they must improve on
        if self._explains_ghosts(obs):
            res = self._refit(obs)
        res = self._fit_size_to_span(obs, res)
        if self._explains_ghosts(obs):  # a few views' hull: the body's girth from the images (GIRTHS), once the
            # pose and the size are fitted (a body too small or a limb astray would be made up for by a stouter one)
            girth = self._fit_girth(obs, res.angles)
            if girth != self.girth:
                log.debug("start: the body's girth %.2f (was %.2f)", girth, self.girth)
                self.girth = girth
                self._use(self.subject.skeleton)
                res = self._refit(obs)
        # the voxels' top is a coarse height: refine the subject's scale from the fitted blobs, or (the default)
        # the bones' lengths. Each round must lower the fit's cost after its EM/IK passes; one that raises it is
        # undone and ends the fit (a guard against feedback between the fit and the pose, which let the hull's
        # torso grow round after round from a start too tall; going on past a worse round and keeping the best
        # was worse: docs/results.md, "Tried and dropped")
        best_fit = (self._fit_cost(res), self.subject.skeleton, res)
        fit_obs = obs.split(BONE_FIT_VOXEL_M)  # the bone fit's voxels (BONE_FIT_VOXEL_M)
        start_body = self.subject.skeleton  # scaled to the voxels' height: the fit's ridge pulls towards it
        for _ in range(FIT_ROUNDS if self.config.fit_bone_lengths else 3):
            if self.config.fit_bone_lengths:
                skel_fit, change = self._fit_bone_lengths(fit_obs, res, start_body)
            else:
                s = self._scale_from_blobs(res)
                # within 10% of the voxels' height: the blobs refine it, they must not run away on bad voxels
                new_h = min(max(self.height_m * s, 0.9 * height, 0.5), 1.1 * height, 2.5)
                skel_fit, change = self.generic.scaled_to_height(new_h), abs(new_h / self.height_m - 1)
            if change < 0.005:
                break
            angles = res.angles.clone()
            self._use(skel_fit.to(pts.device))
            self.angles = self.previous = angles
            res = self._refit(obs)
            cost = self._fit_cost(res)
            log.debug("bone fit round: fit cost %.2f mm, best before %.2f mm", 1e3 * cost, 1e3 * best_fit[0])
            if cost > best_fit[0]:
                _, skel_best, res = best_fit
                self._use(skel_best)
                self.angles = self.previous = res.angles
                break
            best_fit = (cost, self.subject.skeleton, res)
        self.colour = None
        # against the body scaled to the voxels' height, not the fitted one (the bone fit may grow into phantoms)
        raise_deg, fill = self._arms(res)
        check = self.start_check = StartCheck(height, obs.volume_m3() / body_m3, raise_deg, fill, toe, tuple(tried))
        if check.volume_ratio > STARFISH_MAX_VOLUME_RATIO:
            raise InputError(
                f"initialisation: the first frame's voxels hold {check.volume_ratio:.1f} times the volume of a body "
                f"as tall as they are ({height:.2f} m; at most {STARFISH_MAX_VOLUME_RATIO:g} times): not one person "
                "in the starfish pose (phantom volume, or a background that keeps parts of the room or a subject "
                "who stands still). " + START_ADVICE)
        # an arm is missing when its blobs found no voxels where the starfish puts it, or the fit found it hanging
        missing = [side for side, deg, f in zip(("left", "right"), raise_deg, fill)
                   if deg < STARFISH_MIN_ARM_RAISE_DEG or f < self.config.em.min_fill  # NaN fill: not judged
                   ] if self.config.start == "starfish" else []
        if missing:
            raise InputError(
                f"initialisation: the first frame does not look like the starfish pose: the {' and '.join(missing)} "
                f"arm{'s are' if len(missing) > 1 else ' is'} not raised where the starfish puts "
                f"{'them' if len(missing) > 1 else 'it'} (no voxels there, or the fit found "
                f"{'them' if len(missing) > 1 else 'it'} hanging). "
                + START_ADVICE)
        if res.residual_m > self.config.lost_residual_m or res.explained < self.config.min_explained:
            self.subject = None
            pose = " in the starfish pose" if self.config.start == "starfish" else ""
            raise InputError(
                f"initialisation: the first frame does not fit a person{pose} (goal residual "
                f"{1e3 * res.residual_m:.0f} mm, {100 * res.explained:.0f}% of the voxels explained). "
                + START_ADVICE)
        self._unswept = None  # without the sweep the twin turns the start round as it stands
        if self.config.start_limb_sweep:  # on a start the checks took: limbs swept into phantom volume pass them
            self._unswept = res.angles  # the start race's twin turns it round
            self._sweep_finished_limbs(obs, res)
        return self._learn_colour(obs)

    def _sweep_finished_limbs(self, obs: VoxelObservation, res: FrameResult) -> FrameResult:
        """``start_limb_sweep``: the finished start ``res`` with its limbs swept again on the fitted body
        (:func:`~torchtrack.tracking.search.sweep_limbs`). Where the sweep scores higher, its state and ``res`` each
        get the bone fit's EM/IK passes once more (more passes alone change a fit, so the sweep is measured against
        ``res`` tracked again, both in one batch), and the one that scores higher after them is the start (the
        tracker's state; returned)."""
        from torchtrack.tracking.search import score_states, sweep_limbs

        skel, blobs = self.subject.skeleton, self.subject.blobs
        swept, score, before = sweep_limbs(obs, skel, blobs, res.angles)
        if score <= before:
            return res
        finished = self._fit_many(obs, torch.stack([res.angles, swept.to(res.angles)]),
                                  max(2, self.config.init_passes // 3), math.radians(45), predicted=True, hold=True)
        after = score_states(obs, skel, blobs, torch.stack([r.angles for r in finished]))[0]
        log.debug("start: the limbs swept again score %.3f against %.3f; after EM/IK %.3f against %.3f", score,
                  before, float(after[1]), float(after[0]))
        res = finished[1] if float(after[1]) > float(after[0]) else finished[0]
        self.angles = self.previous = res.angles
        return res

    def _learn_colour(self, obs: VoxelObservation) -> FrameResult:
        """The colour model learnt afresh on ``obs`` from the current pose (a start's or a re-acquisition's): the
        frame tracked with the colours free, returned as a re-initialised frame."""
        self.colour = None
        res = self._track(obs, learn_colour=True, max_rot=math.radians(self.config.max_root_rotation_deg))
        self.angles = self.previous = res.angles
        self.colour = res.blobs
        return replace(res, reinitialised=True)

    def _arms(self, res: FrameResult) -> tuple[tuple[float, float], tuple[float, float]]:
        """(left, right) upper-arm angles from hanging (deg) and arm blob fills of a starfish fit
        (:class:`StartCheck`). The raised arms tell the starfish from someone standing: trunk and legs alone fit
        a standing body too, and the voxels of something beside the body (a ghost of an estimated background)
        can make it as wide as a starfish."""
        names, P = self.subject.blobs.names, res.output_points
        out_names = list(self.subject.skeleton.output_names)
        raise_deg, fill = [], []
        for side in ("l", "r"):
            upper = P[out_names.index(f"{side}_elbow")] - P[out_names.index(f"{side}_shoulder")]
            raise_deg.append(math.degrees(math.acos(max(-1.0, min(1.0, -float(upper[2] / upper.norm()))))))
            k = [names.index(f"{side}_{b}") for b in ("upperarm", "forearm") if f"{side}_{b}" in names]
            fill.append(float(res.blobs.fill[k].max()) if k else math.nan)
        return (raise_deg[0], raise_deg[1]), (fill[0], fill[1])

    def _scale_from_blobs(self, res: FrameResult) -> float:
        """Least-squares scale of the fitted blob means about their centroid relative to the model's blobs."""
        model_mean, _ = self.subject.blobs.gaussians(res.bone_frames[None])
        m, f = model_mean[0], res.blobs.mean
        w = (res.blobs.active.to(m.dtype) * res.blobs.fill.clamp(0, 1))[:, None]
        cm, cf = (w * m).sum(0) / w.sum(), (w * f).sum(0) / w.sum()
        return float((w * (f - cf) * (m - cm)).sum() / (w * (m - cm) ** 2).sum().clamp(min=1e-12))
