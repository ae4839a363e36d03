"""Markerless tracking, frame after frame (de Bem §III, Caillette §4): no I/O here.

:class:`MarkerlessTracker` holds one sequence's state and decides what each frame needs; its parts live by job in
:mod:`~torchtrack.tracking.step` (the per-frame step, batched over sequences and hypotheses),
:mod:`~torchtrack.tracking.start` (the automatic start), :mod:`~torchtrack.tracking.race` (the start race),
:mod:`~torchtrack.tracking.recovery` (re-acquisition, lost arms), :mod:`~torchtrack.tracking.bone_fit` (the
subject's bones), :mod:`~torchtrack.tracking.hips` (functional hips) and :mod:`~torchtrack.tracking.config` (its
settings); :mod:`~torchtrack.tracking.lockstep` steps the trackers of several sequences together.

Per frame, from a :class:`~torchtrack.tracking.observation.VoxelObservation`:

1. predict the pose (damped constant velocity of the state vector) and regenerate the blobs from it
   (eq. 17-18): they are EM's starting point and prior;
2. EM of the blobs on the voxels (position and colour; :mod:`torchtrack.blobs.em`); from at most
   ``ghost_max_cameras`` cameras, the ghost voxels the predicted body explains in every view are first given
   ``ghost_weight`` (:mod:`torchtrack.tracking.ghosts`); a blob whose predicted ellipsoid lies more than
   ``MAX_OUTSIDE`` out of the observed volume gives no goals;
3. joint goals from the blobs (Algorithm 2; :class:`~torchtrack.tracking.goals.GoalModel`), the root as the
   bounded Kabsch fit of the trunk goals (the trunk held straight: ``rigid_trunk``), then CCD of the spine and
   limbs onto their goals (eq. 11-16); step 3 is repeated ``refinements`` times, each time from the updated
   bones;
4. check the fit: a frame whose goals the solved skeleton misses by more than ``lost_residual_m`` on average,
   or whose blobs find little of the voxels, counts as diverging; after ``lost_frames`` of them the tracker
   re-initialises from the voxels (the last good pose at four headings and the start's search, compared by the
   search's two-way score and EM/IK's fit cost: :mod:`~torchtrack.tracking.recovery`) instead of drifting. A
   frame without enough voxels (nobody there, unreadable cameras) is not tracked and is returned
   ``valid = False``.
5. (off by default) in an accepted frame, an arm whose hand's blob has been de-activated for ``lost_hand_frames``
   accepted frames is searched for again from hanging (the frame tracked once more with it at rest), which is kept
   where it fits better than the frame tracked once more as it is and does not diverge.

Initialisation (:meth:`MarkerlessTracker.initialize`) is automatic: by default from any pose, by the batched
search of :mod:`torchtrack.tracking.search`, with the starfish start as a fast path where the frame looks like
one (the starfish's kept unless the search's start scores clearly higher); with ``start: starfish`` from the
starfish pose alone (Caillette §4.2): position from the voxels' centroid, heading from the eigenvectors of their
horizontal spread (the arms lie along the main one) and the feet (the toes point forwards), subject height from
the highest voxel. The skeleton is fitted to the voxels and the blobs learn their colours over the first frames.
Or the caller gives an initial state vector and height (de Bem's reusable initialisation, e.g. a previous run's
``poses.npz``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import replace

import torch

from torchtrack.blobs.em import Blobs, prior_blobs
from torchtrack.blobs.model import load_blob_specs
from torchtrack.checks import InputError, check_shape
from torchtrack.skeleton.model import FKResult, Skeleton
from torchtrack.tracking.bone_fit import BONE_FIT_VOXEL_M, BoneFitMixin
from torchtrack.tracking.config import TrackerConfig
from torchtrack.tracking.functional import AxisPivot
from torchtrack.tracking.ghosts import ghost_voxels
from torchtrack.tracking.goals import sole_heights
from torchtrack.tracking.hips import HipsMixin, with_hips_raised
from torchtrack.tracking.recovery import RecoveryMixin
from torchtrack.tracking.voxels import VoxelObservation
from torchtrack.tracking.race import RaceMixin, _Race
from torchtrack.tracking.settle import SettleMixin
from torchtrack.tracking.start import (HEADING_MARGIN_M, STARFISH_MAX_VOLUME_RATIO, STARFISH_MIN_ARM_RAISE_DEG,
                                       StartCheck, StartMixin)
from torchtrack.tracking.step import (MAX_OUTSIDE, FrameResult, StepConfig, StepState, Stepped, Subject, VoxelBatch,
                                      host_tensor, moved_feet, prior_state, track_step)

#: What this module gives its users; the tracker's parts live in config, start, race, recovery, bone_fit, hips, step.
__all__ = ["BONE_FIT_VOXEL_M", "HEADING_MARGIN_M", "STARFISH_MAX_VOLUME_RATIO", "STARFISH_MIN_ARM_RAISE_DEG",
           "FrameResult", "MarkerlessTracker", "StartCheck", "TrackerConfig", "with_hips_raised"]

log = logging.getLogger(__name__)

#: Frame rates a sequence may declare (MarkerlessTracker.set_frame_rate): a video's, from time-lapse to high speed.
MIN_FRAME_RATE, MAX_FRAME_RATE = 0.1, 10000.0


class MarkerlessTracker(StartMixin, RaceMixin, SettleMixin, RecoveryMixin, BoneFitMixin, HipsMixin):
    """Tracks one subject through a sequence of voxel observations (see the module docstring).

    Args:
        skeleton: the generic body (scaled to the subject at initialisation).
        config: tracker settings.
    """

    def __init__(self, skeleton: Skeleton, config: TrackerConfig = TrackerConfig()) -> None:
        self.generic, self.config = skeleton, config
        self.blob_specs = load_blob_specs(config.blobs)  # read once; every subject model reuses them
        self.subject: Subject | None = None
        self.angles: torch.Tensor | None = None  # (D,) last good pose
        self.previous: torch.Tensor | None = None  # (D,) the one before (velocity)
        self.colour: Blobs | None = None  # carries the learnt colour model
        self.lost = 0
        self.held = 0  # image_hold_s: frames in a row the images have held the body out of the observed volume
        self.unchecked = 0  # frames left to check the last re-acquisition in (TrackerConfig.recheck_s)
        self._unheld: list[VoxelObservation | None] = []  # image_hold_s: the invalid frames in a row up to this one
        self.height_m: float | None = None
        self.girth = 1.0  # the subject's girth (Subject), measured at the start
        self.floor_z: float | None = None  # the floor's height for floor contact (set at initialisation)
        self.start_check: StartCheck | None = None  # the last automatic initialisation's measures
        self.start_refusals: list[str] = []  # why each frame before the start was not one to start from
        # hold_lost_feet: each foot's ankle and toe where last observed, and whether they were still then
        self.feet_seen: torch.Tensor | None = None  # (2, 2, 3)
        self.feet_still: torch.Tensor | None = None  # (2, 2) bool
        # lost_hand_frames: accepted frames in a row each hand's blob (left, right) has been de-activated
        self.hands_off = [0, 0]
        # functional_hips: the thighs' axes gathered so far (None: not, or no longer, learning the hips), and
        # the root shift (m, along the pelvis' z) each move of the hips made: the body's version is their count
        self.hips: AxisPivot | None = None
        self.hip_shifts: list[float] = []
        self.bodies: list[Skeleton] = []  # the subject's body before each move
        #: the functional hips' estimate once made (moved or not), else None: each thigh's pivot above the
        #: fitted hip (m) and its information then, both (2,) left, right
        self.hip_estimate: tuple[torch.Tensor, torch.Tensor] | None = None
        self.frame_rate: float | None = None  # the sequence's (set_frame_rate); None: velocity as configured
        self._race: _Race | None = None  # start_race_s: the start turned round, tracked beside this one
        self._unswept: torch.Tensor | None = None  # the last start's state before its limb sweep (start_limb_sweep)
        self._revised: list[tuple[FrameResult, int]] = []  # a won race's or the track back's frames (take_revised)
        self._twin = False  # this tracker races another's start (it starts no race of its own)
        # settle_back_s: the frames since the last start or re-acquisition, each (observation, result, body version)
        self._settle: list[tuple[VoxelObservation, FrameResult, int]] | None = None

    @property
    def _step_config(self) -> StepConfig:
        return StepConfig.of(self.config)

    def set_frame_rate(self, fps: float) -> None:
        """The frame rate of the sequence being tracked (:func:`~torchtrack.tracking.run.track_sequence` sets it
        to the sequence's, ``SequenceFolder.fps``): the prediction's velocity factor is re-derived for it
        (:attr:`prediction_velocity`)."""
        if not MIN_FRAME_RATE <= fps <= MAX_FRAME_RATE:  # NaN fails too
            raise InputError(f"MarkerlessTracker.set_frame_rate: the frame rate must be in [{MIN_FRAME_RATE:g}, "
                             f"{MAX_FRAME_RATE:g}] frames/s, got {fps}")
        self.frame_rate = float(fps)

    @property
    def prediction_velocity(self) -> float:
        """The constant-velocity prediction's factor at the sequence's frame rate: ``TrackerConfig.velocity`` at
        ``velocity_fps``, re-derived for :attr:`frame_rate` (``k = v / (1 - v)`` scaled by ``(velocity_fps /
        fps)^2``, the factor ``k / (1 + k)``; see :class:`TrackerConfig`)."""
        v, at = self.config.velocity, self.config.velocity_fps
        if self.frame_rate is None or at == 0 or v in (0.0, 1.0) or self.frame_rate == at:
            return v  # exactly as configured (k / (1 + k) may round it by an ulp)
        k = v / (1.0 - v) * (at / self.frame_rate) ** 2
        return k / (1.0 + k)

    # ------------------------------------------------------------------------------------ initialisation
    @property
    def initialized(self) -> bool:
        return self.subject is not None

    def _setup(self, height_m: float, device: torch.device) -> None:
        self._use(self.generic.scaled_to_height(height_m).to(device))

    def _use(self, skeleton: Skeleton) -> None:
        self.subject = Subject(skeleton, self.config.ccd, self.blob_specs, self.girth).to(skeleton.lower.device)
        self.height_m = skeleton.height()

    def initialize_from_pose(self, angles: torch.Tensor, height_m: float | None = None, *,
                             skeleton: Skeleton | None = None, floor_z_m: float | None = None) -> None:
        """Start from a known state vector ``angles (D,)`` of a subject ``height_m`` tall (the body model
        scaled to it) or with a given ``skeleton`` (e.g. a previous run's fitted one); give one of the two.
        The floor (for ``floor_contact``) is ``floor_z_m`` when given (e.g. the floor an earlier run measured),
        else the pose's lower sole; the config's ``floor_z_m`` overrides both. The body's girth stays the tracker's
        (the template's, or the one its last automatic start measured: the body refit keeps it)."""
        check_shape(angles, (self.generic.num_dofs,), "angles")
        if (height_m is None) == (skeleton is None):
            raise InputError("initialize_from_pose: give the subject's height_m or its skeleton")
        if skeleton is None:
            self._setup(height_m, angles.device)
        else:
            self._use(skeleton.to(angles.device))
        self._start_hips(learn=skeleton is None)
        self.angles = self.previous = angles.clone()
        self.colour = None
        self.lost = self.held = self.unchecked = 0
        self._unheld = []
        self.hands_off = [0, 0]
        self._remember_feet()
        if floor_z_m is None:
            floor_z_m = float(sole_heights(self.feet_seen, self.subject.ankle_height).min())
        self._set_floor(floor_z_m)

    def _set_floor(self, soles_z: float) -> None:
        self.floor_z = soles_z if self.config.floor_z_m is None else float(self.config.floor_z_m)


    def reset(self) -> None:
        """Back to uninitialised: the next frame with a person in it starts the track again (the automatic start);
        the refusals of earlier starts are forgotten."""
        self._clear()
        self.start_refusals = []

    def _clear(self) -> None:
        self._race, self._revised, self._settle, self._unswept = None, [], None, None
        self.subject = self.angles = self.previous = self.colour = self.height_m = self.floor_z = None
        self.girth = 1.0
        self.hips, self.hip_shifts, self.bodies, self.hip_estimate = None, [], [], None
        self.feet_seen = self.feet_still = None
        self.lost = self.held = self.unchecked = 0
        self._unheld = []
        self.hands_off = [0, 0]


    # ------------------------------------------------------------------------------------------ tracking
    def _remember_feet(self) -> None:
        """The feet of the current pose as last observed and still (at initialisation)."""
        sub = self.subject
        self.feet_seen = sub.skeleton.forward(self.angles[None]).joints[0, sub.feet]  # (2, 2, 3)
        self.feet_still = torch.ones(self.feet_seen.shape[:2], dtype=torch.bool, device=self.feet_seen.device)

    def _update_feet(self, res: FrameResult, feet: tuple[torch.Tensor, torch.Tensor] | None = None) -> None:
        """After an accepted frame: each foot joint the observation gave a goal is remembered where the solved
        pose put it, and counts as still when it moved under ``hold_max_step_m`` since it was last seen, however
        many frames ago (a foot that comes back elsewhere after a gap is not held until it is seen still).
        ``feet``: that update already made for this result (:func:`moved_feet` of many trackers at once)."""
        if self.feet_seen is None or res.feet is None:
            return
        if feet is None:
            feet = moved_feet(*res.feet, self.feet_seen, self.feet_still, self.config.hold_max_step_m)
        self.feet_seen, self.feet_still = feet

    def _regenerate(self, angles: torch.Tensor) -> tuple[FKResult, Blobs]:
        """The prior blobs at ``angles (D,)`` with the colour model, and the forward kinematics they came from."""
        sub = self.subject
        fk = sub.skeleton.forward(angles[None])
        mean, cov = sub.blobs.gaussians(fk.bone_frames)
        prior = prior_blobs(mean[0], cov[0])
        if self.colour is not None:
            prior = replace(prior, colour_mean=self.colour.colour_mean, colour_cov=self.colour.colour_cov,
                            colour_known=self.colour.colour_known)
        return fk, prior

    @staticmethod
    def _inside_volume(obs: VoxelObservation, blobs: Blobs) -> torch.Tensor:
        """(K,) bool: the blobs with at most ``MAX_OUTSIDE`` of their ellipsoid out of the observed volume."""
        return obs.outside(blobs.mean, blobs.cov) <= MAX_OUTSIDE

    def _explains_ghosts(self, obs: VoxelObservation) -> bool:
        """Whether the ghost test runs on ``obs``: ``ghost_weight`` < 1, the cameras' centres known, and at most
        ``ghost_max_cameras`` in the rig (readable in this frame or not)."""
        cfg = self.config
        return (cfg.ghost_weight < 1.0 and obs.camera_centres is not None
                and obs.camera_centres.shape[0] <= cfg.ghost_max_cameras)

    def _ghost_weights(self, obs: VoxelObservation, prior: Blobs) -> torch.Tensor:
        """The voxels' EM weights with the ghosts the predicted blobs ``prior`` explain away lowered by
        ``ghost_weight`` (:mod:`torchtrack.tracking.ghosts`)."""
        cfg = self.config
        if not self._explains_ghosts(obs):
            return obs.weights
        seen = torch.isfinite(obs.colours).all(-1) & obs.cameras_valid.to(obs.points.device)
        # only blobs the last accepted frame's voxels filled may explain a ray: not a limb the views lost
        covers = self.colour.active if self.colour is not None else None
        ghost = ghost_voxels(obs.points, seen, obs.camera_centres.to(obs.points), prior.mean, prior.cov,
                             cfg.ghost_inside_scale, cfg.ghost_cover_scale, covers,
                             self_scale=cfg.ghost_self_scale)
        return torch.where(ghost, obs.weights * cfg.ghost_weight, obs.weights)

    def _step_state(self, angles: torch.Tensor, previous: torch.Tensor, velocity: float) -> StepState:
        """The step's start from states ``angles``, ``previous (H, D)`` with this tracker's colour model, held feet
        and floor (the same for all H)."""
        H, K = angles.shape[0], self.subject.blobs.num_blobs
        kw = prior_state(angles, K)
        if self.colour is not None:
            c = self.colour
            kw.update(colour_mean=c.colour_mean.expand(H, K, 3), colour_cov=c.colour_cov.expand(H, K, 3, 3),
                      colour_known=c.colour_known.expand(H, K), covers=c.active.expand(H, K))
        if self.feet_seen is not None:
            kw.update(feet_seen=self.feet_seen.expand(H, 2, 2, 3), feet_still=self.feet_still.expand(H, 2, 2))
        floor = math.nan if self.floor_z is None else self.floor_z
        return StepState(angles, previous, angles.new_full((H,), velocity), floor_z=angles.new_full((H,), floor),
                         **kw)

    def _results(self, st: Stepped, host: Sequence[Sequence[float]] | None = None) -> list[FrameResult]:
        """The step's batch as one :class:`FrameResult` per row (one wait for the host, or none where ``host`` gives
        its residuals and explained shares, read already by a caller that read more in the same wait)."""
        residual, explained = host or torch.stack([st.residual_m.double(), st.explained.double()]).tolist()  # exact
        blobs = [Blobs(*v) for v in zip(*(getattr(st.blobs, f.name).unbind(0) for f in dataclasses.fields(Blobs)))]
        return [FrameResult(st.angles[h], st.output_points[h], st.confidence[h], True, residual[h], explained[h],
                            False, blobs[h], st.bone_frames[h], (st.feet[h], st.feet_observed[h]))
                for h in range(len(residual))]

    def _track(self, obs: VoxelObservation, learn_colour: bool, max_rot: float, predicted: bool = True,
               hold: bool = True) -> FrameResult:
        """One frame from the predicted pose (:func:`~torchtrack.tracking.step.track_step`); ``predicted``: trust
        the prediction, to explain ghost voxels away against it and to silence the blobs it puts out of the volume
        (off where it is only a guess: the heading search of initialisation and re-acquisition, whose hypotheses
        must be scored on the same goals); ``hold``: hold unseen planted feet where they were last seen (off in
        re-acquisition's search)."""
        state = self._step_state(self.angles[None], self.previous[None], self.prediction_velocity)
        batch = VoxelBatch.of([obs], self.config.ghost_max_cameras)
        return self._results(track_step(self.subject.stack, batch, state, self._step_config, learn_colour,
                                        max_rot, predicted, hold))[0]

    def _fit_many(self, obs: VoxelObservation, starts: torch.Tensor, passes: int, max_rot: float,
                  predicted: bool = False, hold: bool = False) -> list[FrameResult]:
        """Each of H states ``starts (H, D)`` fitted to ``obs`` by ``passes`` rounds of :meth:`_track` without
        colours or velocity (as ``_track(obs, learn_colour=False, max_rot, predicted, hold)`` from each round's
        result), all H in one batch: by default without the prediction's trust or held feet, the hypotheses of a
        re-acquisition. The tracker's state is not changed."""
        if self.colour is not None:
            raise InputError("_fit_many fits without colours: the tracker's colour model must be dropped first")
        batch = VoxelBatch.of([obs], self.config.ghost_max_cameras).repeat(starts.shape[0])
        state = starts
        for _ in range(passes):
            st = track_step(self.subject.stack, batch, self._step_state(state, state, 0.0), self._step_config,
                            False, max_rot, predicted=predicted, hold=hold)
            state = st.angles
        return self._results(st)

    def _invalid(self) -> FrameResult:
        sub = self.subject
        if sub is None or self.angles is None:
            like = self.generic.lower
            J, nb = len(self.generic.output_names), len(self.generic.bone_names)
            return FrameResult(torch.full_like(like, torch.nan), like.new_full((J, 3), torch.nan), like.new_zeros(J),
                               False, math.nan, 0.0, False, None, like.new_full((nb, 4, 4), torch.nan))
        fk = sub.skeleton.forward(self.angles[None])
        return FrameResult(self.angles.clone(), fk.output_points[0], torch.zeros(fk.output_points.shape[1]).to(
            self.angles), False, math.nan, 0.0, False, None, fk.bone_frames[0])

    def _without_floor_band(self, obs: VoxelObservation) -> VoxelObservation:
        """``obs`` with no weight in the floor band of its rig (``TrackerConfig.floor_band_m``)."""
        return obs.without_floor_band(self.config.floor_band(int(obs.cameras_valid.shape[0])))

    def _has_person(self, obs: VoxelObservation) -> bool:
        return obs.num_observed >= self.config.min_voxels and obs.volume_m3() >= self.config.min_volume_m3

    def skip(self) -> FrameResult:
        """A frame that cannot be observed (an unreadable camera frame): not tracked, ``valid = False``; the
        next frame predicts from the last good pose without velocity."""
        self.previous = self.angles
        self._settle = None  # the frames to track back end at a gap
        res = self._invalid()
        self._hold_back(None, res, self.angles is not None)
        if self._race is not None:
            twin = self._race.twin
            version = twin.body_version
            self._race_step(None, res, twin.skip(), version)
        return res

    def step(self, obs: VoxelObservation) -> FrameResult:
        """Track one frame (initialising on the first frame with a person in it). A start race's end, or the
        track back from a settled track (``settle_back_s``), may revise the frames before (:meth:`take_revised`)."""
        racing = self._race is not None  # a race started by this frame's initialisation has scored it already
        version = self.body_version
        started = self.angles is not None
        res = self._step(obs)
        self._hold_back(obs, res, started)
        if racing:  # the twin races without a race of its own: its frame is its _step
            twin = self._race.twin
            version = twin.body_version
            self._race_step(obs, res, twin._step(obs), version)
        self._settle_step(obs, res, version)
        return res

    def _hold_back(self, obs: VoxelObservation | None, res: FrameResult, started: bool) -> None:
        """``image_hold_s``: keeps the observations of the invalid frames in a row (at most ``image_hold_s``; None
        for an unreadable one), and where a re-acquisition ends them (not the first start: the frames before it
        stay invalid), the frames before it that the images hold (:meth:`_held_back`) revise them
        (:meth:`take_revised`)."""
        hold_frames = self._hold_frames()
        if hold_frames < 1 or self._twin or not started:
            return
        if not res.valid:
            self._unheld = (self._unheld + [obs])[-hold_frames:]
            return
        unheld, self._unheld = self._unheld, []
        if not (res.reinitialised and unheld and not self._revised):
            return
        if self._race is not None:  # the race this re-acquisition started holds them back anew if its twin wins
            self._race.unheld = unheld
        back = self._held_back(unheld, res)
        if back:
            log.debug("image hold: %d frames before the re-acquisition held in the images", len(back))
            self._revised = [(r, self.body_version) for r in back] + [(res, self.body_version)]

    def finish(self) -> None:
        """The sequence has ended: a start in its last second gets what an earlier start gets later. A start race
        still on is decided on its frames since the body moved where they are at least half the race (else the
        search's start stays: a still body looks the same turned round, and a frame or two of motion is noise), and
        the frames since the last start or re-acquisition, where they did not yet hold ``settle_back_s``, are
        tracked back from the last one. :meth:`take_revised` then gives the frames these revise."""
        if self._race is not None:
            race = self._race
            if race.moved_at is None or len(race.fits) - race.moved_at < max(1, self._race_frames() // 2):
                self._race = None  # too few frames since the body moved to tell: the search's start stays
            else:
                self._decide_race()
                self._settle_revised()
        if self._settle is not None:
            self._settle_back()

    def _step(self, obs: VoxelObservation) -> FrameResult:
        held = self._held_in_images(obs)
        if held is not None:
            return held
        if not self._has_person(obs):
            self.previous = self.angles  # no velocity across a gap
            self.lost = max(self.lost, self.config.lost_frames)  # re-acquire when the person comes back
            self.hands_off = [0, 0]
            return self._invalid()
        if self.config.em_cell_m > 0:
            obs = obs.pooled(self.config.em_cell_m)
        if not self.initialized:
            try:
                return self.initialize(obs)
            except InputError as exc:  # not a frame to start from: the next one may be
                self.start_refusals.append(str(exc))
                return self._invalid()
        obs = self._without_floor_band(obs)  # the start keeps the floor's voxels (see config)
        if self.angles is not None and self.lost >= self.config.lost_frames:
            return self._reacquire(obs)
        res = self._track(obs, learn_colour=True, max_rot=math.radians(self.config.max_root_rotation_deg))
        if self.unchecked > 0 and self._race is None and not self._twin:
            found = self._check_reacquired(obs, res)
            if found is not None:
                return found
        return self.accept(obs, res)

    def routine_ready(self, obs: VoxelObservation) -> bool:
        """For a driver that runs the plain per-frame step itself (several sequences in lockstep,
        :class:`~torchtrack.tracking.lockstep.Lockstep`): False where this tracker's own state (not started, lost,
        racing a start, a re-acquisition to check) or the voxels' count rules the plain step out and the frame goes
        through :meth:`step`; else :func:`~torchtrack.tracking.recovery.routine_tests` decides, and :meth:`accept`
        takes the result."""
        return not (self._race is not None or self.subject is None or self.angles is None or self.unchecked > 0
                    or self.lost >= self.config.lost_frames or obs.num_observed < self.config.min_voxels)

    def routine_obs(self, obs: VoxelObservation) -> VoxelObservation:
        """``obs`` as the plain step takes it (as :meth:`_step` makes it: merged per ``em_cell_m``, then the floor
        band)."""
        return self._without_floor_band(obs.pooled(self.config.em_cell_m) if self.config.em_cell_m > 0 else obs)

    @staticmethod
    def step_states(trackers: Sequence[MarkerlessTracker]) -> StepState:
        """The batched step's start for several started trackers, row ``b`` tracker ``b``'s (its
        :meth:`_step_state` of its pose): a field's rows stacked at once, not a state built per tracker."""
        if len(trackers) == 1:
            t = trackers[0]
            return t._step_state(t.angles[None], t.previous[None], t.prediction_velocity)
        like = trackers[0].angles
        prior = {k: v[0] for k, v in prior_state(like[None], trackers[0].subject.blobs.num_blobs).items()}

        def rows(field: str, of: Callable[[MarkerlessTracker], torch.Tensor | None]) -> torch.Tensor:
            return torch.stack([prior[field] if (v := of(t)) is None else v for t in trackers])

        def colour(field: str) -> Callable[[MarkerlessTracker], torch.Tensor | None]:
            return lambda t: None if t.colour is None else getattr(t.colour, field)

        return StepState(
            torch.stack([t.angles for t in trackers]), torch.stack([t.previous for t in trackers]),
            host_tensor([t.prediction_velocity for t in trackers], like),
            colour_mean=rows("colour_mean", colour("colour_mean")), colour_cov=rows("colour_cov", colour("colour_cov")),
            colour_known=rows("colour_known", colour("colour_known")), covers=rows("covers", colour("active")),
            feet_seen=rows("feet_seen", lambda t: t.feet_seen),
            feet_still=rows("feet_still", lambda t: None if t.feet_seen is None else t.feet_still),
            floor_z=host_tensor([math.nan if t.floor_z is None else t.floor_z for t in trackers], like))

    def accept(self, obs: VoxelObservation, res: FrameResult,
               feet: tuple[torch.Tensor, torch.Tensor] | None = None) -> FrameResult:
        """Take in the plain step's result ``res`` on ``obs`` (as :meth:`routine_obs` makes it): a diverging frame
        counts towards re-acquisition (which it starts after ``lost_frames``), an accepted one moves the pose, the
        colour model, the held feet and the functional hips on (and may search for a lost arm). ``feet``: the held
        feet's update for ``res`` where the driver made it for many trackers at once (:func:`moved_feet`)."""
        if self._diverging(res):
            self.lost += 1
            if self.lost >= self.config.lost_frames:
                return self._reacquire(obs)
            self.previous = self.angles  # keep the last good pose, without velocity
            return replace(res, valid=False)
        self.lost = self.held = 0
        res, found = self._search_lost_arms(obs, res)
        self.previous, self.angles = self.angles.clone(), res.angles
        for arm in found:  # no velocity across the search's jump (it ran off again the way it came)
            self.previous[arm] = res.angles[arm]
        self.colour = res.blobs  # the colour model follows accepted frames only
        self._update_feet(res, None if found else feet)  # a lost arm found: another result
        if self.hips is not None and int(obs.cameras_valid.sum()) >= self.config.functional_hips_min_cameras:
            self._learn_hips(res)
        return res

    @staticmethod
    def _fit_cost(res: FrameResult) -> float:
        """How badly a hypothesis fits (initialisation and re-acquisition pick the least): metres of goal
        residual plus 0.1 m per unit of voxel weight left unexplained."""
        return res.residual_m + 0.1 * (1.0 - res.explained)

    def _diverging(self, res: FrameResult) -> bool:
        return res.residual_m > self.config.lost_residual_m or res.explained < self.config.min_explained
