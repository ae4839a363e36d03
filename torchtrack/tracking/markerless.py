"""Markerless tracking, frame after frame (de Bem §III, Caillette §4): no I/O here.

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
   search's two-way score and EM/IK's fit cost: :meth:`MarkerlessTracker._reacquire`) instead of drifting. A
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

import copy
import dataclasses
import logging
import math
from dataclasses import dataclass, field, replace
from collections.abc import Sequence
from typing import Any

import torch

from torchtrack.blobs.em import Blobs, EMConfig, fit_blobs, prior_blobs
from torchtrack.blobs.model import BlobModel, blob_volumes, load_blob_specs
from torchtrack.blobs.shape import ShapeFrame, ShapeModel, fit_shape, fit_shape_frames
from torchtrack.checks import InputError, check_shape, config_section
from torchtrack.conventions import LANDMARKS
from torchtrack.skeleton.ik import CCDConfig
from torchtrack.skeleton.model import FKResult, Skeleton, root_rotation_matrix
from torchtrack.tracking.functional import AxisPivot
from torchtrack.tracking.ghosts import ghost_voxels
from torchtrack.tracking.goals import sole_heights
from torchtrack.tracking.observation import VoxelObservation
from torchtrack.tracking.step import (CCD_GOALS, MAX_OUTSIDE, StepConfig, StepState, Stepped, Subject,
                                      VoxelBatch, prior_state, track_step)

log = logging.getLogger(__name__)

#: hold_lost_feet: after a re-acquisition, a remembered foot farther than this from the re-acquired pose's is no
#: longer held (the subject may have moved on while it was lost).
REACQUIRED_FOOT_M = 0.1
#: Bones whose lengths are fitted together at initialisation (left and right tied).
#: Each limb's two long bones share one scale and the pelvis, hands and feet another (too small to measure
#: apart); torso and head are fitted separately, and the neck's height on the torso (NECK_JOINT). Real subjects'
#: proportions differ from the template's, which one scale cannot follow (docs/results.md, "Tracker settings").
BONE_GROUPS: tuple[tuple[str, ...], ...] = (
    ("pelvis", "l_hand", "r_hand", "l_foot", "r_foot"), ("torso",), ("head",),
    ("l_upperarm", "r_upperarm", "l_forearm", "r_forearm"), ("l_thigh", "r_thigh", "l_shank", "r_shank"))

#: functional_hips: the thigh blobs whose axes locate the hips, and the joints (on the pelvis) they move. Only a
#: shift up, of at most FUNCTIONAL_HIPS_MAX_M and leaving the pelvis at least a fifth of its length, is made: the
#: bone fit's bias runs up (EM gives the thighs' tops to the pelvis blob), so a pivot below the fitted hips is the
#: axes' error (docs/results.md, "Tracker settings"); anything else is logged and the body left as fitted.
THIGH_BLOBS, HIP_JOINTS, SPINE_JOINT = ("l_thigh", "r_thigh"), ("l_hip_flex", "r_hip_flex"), "spine_flex"
HIP_FRAMES = ("l_thigh", "r_thigh")  # the hips' positions among JOINT_FRAMES
FUNCTIONAL_HIPS_MAX_M = 0.08

#: The neck's height on the torso is fitted on top of the torso's scale (which moves the neck and the shoulders
#: together): subjects differ in how far the neck base sits above the shoulder joints. Finite-difference step (m).
NECK_JOINT, NECK_STEP_M = "neck_flex", 0.1

#: Frame rates a sequence may declare (MarkerlessTracker.set_frame_rate): a video's, from time-lapse to high speed.
MIN_FRAME_RATE, MAX_FRAME_RATE = 0.1, 10000.0

#: The bone fit's ridge on each group's change relative to the body the fit started from (the template scaled to
#: the voxels' height; for the torso its length, which is the neck's height on it), and on the neck's shift in
#: NECK_STEP_M towards each round's body (with the torso's length held, that shift sets the shoulders' height).
#: Towards the start because rounds towards their own last body drift along what the voxels hardly tell apart, the
#: torso's length against the head's (docs/results.md, "Tracker settings"; the shoulders held as well: "Tried and
#: dropped").
BONE_FIT_RIDGE = 0.02

#: TrackerConfig.bone_fit's choices.
BONE_FITS = ("blobs", "shape")
#: How the first pose is found (TrackerConfig.start).
STARTS = ("search", "starfish")
#: While lost, the re-acquisition searches for the whole state (a second or more on a CPU) every this many frames.
REACQUIRE_SEARCH_EVERY = 5
#: Re-acquisition: of its fits that pass the checks, those within this of the best two-way score
#: (:func:`~torchtrack.tracking.search.score_states`, 0-1) compete by EM/IK's fit cost. The score tells a wrong
#: heading or pose from the right one, but it also prefers a limb no view shows (a stance leg learnt into the
#: background) moved onto voxels; the fit cost leaves such a limb where the pose puts it.
REACQUIRE_SCORE_MARGIN = 0.05
#: The search's start is refused where more of the body than this lies out of the observed volume.
START_MAX_OUTSIDE = 0.2

#: A start frame whose voxels hold two separate people is refused (torchtrack tracks one person). A connected part
#: of the voxels (:meth:`VoxelObservation.parts`) is a person when it is at least PERSON_MIN_HEIGHT_M tall (a deep
#: squat still is) and holds at least PERSON_MIN_VOLUME of the smallest body the search looks for: floor shadows,
#: a foot's stray voxels and a phantom column of an estimated background are lower or smaller.
PERSON_MIN_HEIGHT_M = 1.0
PERSON_MIN_VOLUME = 0.5

#: The shape fit's ridge (bone_fit "shape"; the same form as BONE_FIT_RIDGE's, on an energy in m^2, a mean of
#: squared distances between the voxels and the body: 2e-6 weighs a group's 10 % change like 0.14 mm of mean
#: distance). Weak on purpose: ten times stronger held the CMU walks' torsos long, and without it the fit came
#: out the same (docs/results.md, "Tracker settings").
SHAPE_FIT_RIDGE = 2e-6

#: The shape fit's starts, (the neck's shift in NECK_STEP_M, the head's relative change): the union's energy has
#: local minima along the neck's height against the head's length, and which one a single start falls into is
#: fragile (it moved with the distance field's margin and the arithmetic's precision; docs/results.md,
#: "Tracker settings").
SHAPE_FIT_STARTS = ((0.0, 0.0), (-0.75, 0.0), (-0.75, 0.25), (-1.5, 0.0), (-1.5, 0.25))

#: Rounds of the bone fit at initialisation, each followed by EM/IK passes, at most (it stops under a 0.5 %
#: change, or at a round that fits worse). Eight because three left the CMU bodies' torsos halfway to their
#: length (docs/results.md, "Tracker settings").
FIT_ROUNDS = 8

#: The bone fit's EM sees the voxels split to at most this size (:meth:`VoxelObservation.split`): the hull's
#: coarse interior cubes (6-12 cm) each went whole to one blob, and at the hips they gave the thighs' tops to the
#: pelvis and the legs came out short (docs/results.md, "Tracker settings"). The Bayesian grid's voxels (3 cm) are
#: not split.
BONE_FIT_VOXEL_M = 0.03

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

#: The start race (``TrackerConfig.start_race_s``): the start turned round replaces the search's start only if its
#: mean fit cost (:meth:`MarkerlessTracker._fit_cost`) over the race is lower, its mean two-way score
#: (:func:`~torchtrack.tracking.search.score_states`, 0-1) not lower by more than this, and one of the two wins
#: clearly: the score by more than this, or the cost by :data:`START_RACE_COST_RATIO`. On a 4-camera hull's ghosts
#: the score alone preferred the turned round twin of a wrong start, which was wronger; on a walk from a starfish
#: the two scored the same and only the fit cost (knees that bend one way) told them apart (docs/results.md,
#: "The start race"). The starfish's fast path takes the same margin: a searched start replaces the starfish's only
#: if it scores higher by more than this.
START_RACE_MARGIN = 0.01
#: The fit cost's clear win in the start race: the twin's mean cost below this fraction of the start's.
START_RACE_COST_RATIO = 0.8
#: The race's ``start_race_s`` counts from the first frame where the body has moved (a landmark of the start's
#: track this far from where the start put it, relative to the pelvis), and only the frames from there decide it: a
#: still body's silhouette is the same turned round, and over such frames the race would only compare how the two
#: fits happened to settle, which turned a 4-camera squat's start round (docs/results.md, "The start race").
START_RACE_MOVED_M = 0.1
#: A race waits this long for the body to move, then is decided on all its frames.
START_RACE_WAIT_S = 2.0

#: What every refusal of the automatic initialisation tells the user to do.
START_ADVICE = ("The tracker starts at the first frame that shows one whole person in the capture volume; with the "
                "starfish start (tracker start: starfish), in the starfish pose. Or give an initial pose with "
                "--init-pose START.npz: a poses.npz of this subject whose first valid frame is the pose (an earlier "
                "run's output), or one fitted to 3D keypoints of the first frame by `torchtrack init-pose "
                "KEYPOINTS.trc --out START.npz`")


@dataclass(frozen=True)
class TrackerConfig:
    """Tracker settings (``configs/markerless.yaml`` holds the defaults a run uses).

    Attributes:
        em, ccd: EM and CCD settings.
        refinements: goals -> root -> CCD passes per frame (1: de Bem's Algorithm 2 once; each further pass starts
            from the bones the last one solved). One by default: a second fits some synthetic 4-camera motions
            better and the real Pose2Sim demo worse (docs/results.md, "Tracker settings").
        max_root_rotation_deg: bound on the root's change of orientation per pass (no front/back flips).
        velocity: factor of the constant-velocity prediction (0 = previous pose), at ``velocity_fps``.
        velocity_fps: the frame rate ``velocity`` is set for (0: use it as it is at every rate). At another rate
            (:meth:`MarkerlessTracker.set_frame_rate`) the factor is re-derived as the gain of a velocity read off
            one frame difference, a heuristic: with per-frame motion d and a velocity estimate whose noise is s
            per frame (the last pose taken as exact), the prediction error is least at ``v = d^2 / (d^2 + 2 s^2)``;
            d scales with 1 / fps and s does not, so ``k = v / (1 - v)`` scales with ``(velocity_fps / fps)^2``
            and the factor is ``k / (1 + k)``: 0.5 at 30 fps is 0.2 at 60 fps
            (:attr:`MarkerlessTracker.prediction_velocity`). The 60 fps Pose2Sim demo tracks best near 0.2 and the
            30 fps synthetic sequences at 0.5 (docs/results.md, "Tracker settings").
        min_voxels, min_volume_m3: below either, the frame has nobody in it (valid = False).
        lost_residual_m: mean goal-to-joint distance above which a frame counts as diverging.
        min_explained: fraction of the voxel weight the blobs must take (else diverging).
        lost_frames: diverging frames in a row before re-initialising.
        init_passes: EM/IK passes on the first frame during initialisation.
        start: how the first pose is found. ``"search"``: from any pose, by the batched search of
            :mod:`torchtrack.tracking.search` (hypotheses of the whole state scored against the voxels, the best
            ``start_hypotheses`` finished by EM/IK; its random steps seeded by ``search_seed``), and the starfish
            start too where the frame passes its checks, kept unless the search's scores clearly higher
            (``START_RACE_MARGIN``); ``"starfish"``: the starfish start (Caillette §4.2) alone, which refuses any
            other pose.
        start_real_poses: the search also starts from real captured poses
            (:func:`~torchtrack.tracking.search.real_pose_prior`). Turn it on for a subject in crouched, twisted or
            reaching poses seen by 8 or more cameras, where more starts land right. Off by default: beside phantom
            volume it can take a taller body with its arms raised into the phantom, and one stress sequence
            tracked worse (docs/results.md, "Real poses in the prior").
        start_prior_exclude: the search leaves out the real captures' poses whose capture's name contains one of
            these (:func:`~torchtrack.tracking.search.real_pose_prior`): for evaluations on the captures the prior
            was built from, which leave their subject out (scripts/eval_start.py, eval_robustness.py).
        start_race_s: after a searched start (and a re-acquisition, with that start), the start turned round (the
            same silhouette facing the other way, which one frame's voxels cannot tell from it:
            :func:`~torchtrack.tracking.search.turned_round`) is tracked beside it for this long from the body's
            first move (``START_RACE_MOVED_M``), and the one whose poses fit the voxels better from that move on
            (EM/IK's fit cost lower, the mean two-way score not lower by more than ``START_RACE_MARGIN``, and one
            of the two clearly better: the score by that margin or the cost by ``START_RACE_COST_RATIO``) is
            kept, its frames replacing the other's
            (:meth:`MarkerlessTracker.take_revised`): a body's motion shows which way it faces, as knees and elbows
            bend one way only (0: off).
        fit_bone_lengths: at initialisation fit the bones' lengths and the neck's height to the blobs (else one
            scale for the whole body). On by default: real people's proportions differ from the template's (the
            CMU walks' torsos are 0.25 m, the template's scaled to their height 0.37; docs/results.md,
            "Tracker settings").
        bone_fit: what the bone fit fits. ``"blobs"``: the means and lengths of blobs EM fitted to the voxels
            without priors, by linear least squares; ``"shape"``: the union of the body's ellipsoids to the voxels
            themselves (:mod:`torchtrack.blobs.shape`), which EM's sharing of the voxels between overlapping blobs
            does not bias (the pelvis' over the thighs' tops, the head's over the neck), but which takes
            silhouette holes and ghost volume as the body's shape. Not the default: it helps the synthetic CMU
            walks but costs the template bodies' heads (a head's top the voxels lack shrinks it) and the 4-camera
            squat (docs/results.md, "Tracker settings").
        em_cell_m: merge the voxels per cell of this size before EM (0: off); for fine hulls, whose EM cost
            grows with the voxel count while the blobs need no such detail.
        blobs: blob config file (``configs/`` name or path).
        floor_contact: keep the lowest foot on the floor (Caillette §4.2: at least one part of the body touches
            the floor; :func:`~torchtrack.tracking.goals.floor_contact`). Off for jumps and running.
        floor_z_m: the floor's height for the contact (m); None: the soles' height at initialisation (the
            lowest voxels of the starfish frame, or the initial pose's lower toe site).
        ghost_weight: factor on the EM weight of ghost voxels, those the predicted body explains in every view
            (:mod:`torchtrack.tracking.ghosts`; 1: off). ``explained`` still counts their full weight.
            ghost_max_cameras: only for rigs of at most this many cameras: from more, the hull holds few ghosts and
            the test takes more real voxels (at the seams between blobs) than ghosts (docs/results.md, "Tracker
            settings"). ghost_inside_scale, ghost_cover_scale: its ellipsoid scales (a voxel inside the predicted
            blobs grown by the first is never a ghost; a ray through them grown by the second is explained).
            ghost_self_scale: a blob does not explain the rays of voxels inside its own ellipsoid grown by this (0: it
            does; it acts only above ``ghost_inside_scale``), so that a limb that moved past its prediction, seen from
            cameras that look down along it, can follow its voxels.
        hold_lost_feet: IK weight of the goals that hold a foot where it was last observed while no view shows
            it (0: off): the ankle and toe whose goals' confidence falls under ``hold_min_confidence`` and that moved
            less than ``hold_max_step_m`` between their last two observed frames (a planted foot, not a swinging one:
            2 cm a frame is 0.6 m/s at 30 fps; a foot seen again elsewhere after a gap is not held until it is seen
            still) keep their last observed positions as goals. The residual and the confidences stay the
            observation's. It helps the Pose2Sim demo, whose stance leg the background holds (docs/results.md,
            "Tracker settings"). The initial pose counts as observed, so a foot it puts wrong that no view shows stays
            wrong (with ``floor_contact`` the support foot's held goals are then lowered onto the floor). Nothing is
            held during initialisation's or re-acquisition's search, and after a re-acquisition a remembered foot
            farther than ``REACQUIRED_FOOT_M`` from the new pose's is let go.
        functional_hips: move the hips, once, to where the thighs pivot (:mod:`torchtrack.tracking.functional`)
            when each thigh's axes have gathered this much information (the sum over frames of its blob's fill
            times sin^2 of the axis' angle off its mean; 0: off). The pelvis' origin rises with the hips (the
            spine's joint on it comes down as much) and the thighs lengthen as much, so that the rest of the
            body stays where it is; the tracked state moves its root up as much. Only for a body the tracker
            fitted (automatic initialisation, or :meth:`MarkerlessTracker.initialize_from_pose` with a height),
            not for a given skeleton. The frames tracked before are re-stated in the moved body by
            :func:`~torchtrack.tracking.run.track_sequence` (:meth:`MarkerlessTracker.restate`).
            functional_hips_min_cameras: the thighs' axes are learnt only from rigs of at least this many
            cameras: the ghost volumes of four views bend the thigh blobs' axes and put the pivots below the
            fitted hips (docs/results.md, "Tracker settings").
        lost_hand_frames: a hand whose blob has been de-activated (empty, Caillette §4.3) for this many accepted
            frames has lost its arm, which is searched for again: the frame is tracked once more from its solution
            with that arm's five DOFs (``ARM_DOFS``) at rest, hanging beside the body, and once more as it is; the
            search is kept if its fit's cost (:meth:`MarkerlessTracker._fit_cost`) is the lower and it does not
            diverge, and the arm's DOFs then carry no velocity into the next frame. Found or not, the next search is
            this many frames on (a hand no view shows costs two more passes per this many frames); a frame with
            nobody and a re-acquisition start the count again (0: off). De-activation alone only waits for the hand
            to fill again where the arm predicts it, which it does not once the arm has drifted off its voxels
            (scripts/eval_tracking.py --blob-activity). Off by default: it helps the 4-camera hull, but on the
            Pose2Sim demo a search kept in the first pass moved the refinement's later passes for the worse
            (docs/results.md, "Tracker settings").
        rigid_trunk: fit the root to the trunk goals with the spine straight, and let CCD bend the spine from
            straight (else the root is fitted to the trunk as currently bent). The hips lie on the pelvis' pitch
            axis, so the goals hardly tell a tilted pelvis with the spine and hips bent to make up for it from an
            upright one; fitted with the current bend, the split drifted (the pelvis pitched far back, the thighs
            at their extension limit; docs/results.md, "Tracker settings"). The price: a real spine bend is taken
            by the pelvis and the hips (the landmarks move little).
    """

    em: EMConfig = field(default_factory=EMConfig)
    ccd: CCDConfig = field(default_factory=lambda: CCDConfig(damping=0.3, sweeps=8))
    refinements: int = 1
    max_root_rotation_deg: float = 25.0
    velocity: float = 0.5
    velocity_fps: float = 30.0
    min_voxels: int = 30
    min_volume_m3: float = 0.01
    lost_residual_m: float = 0.08
    min_explained: float = 0.6
    lost_frames: int = 3
    init_passes: int = 12
    start: str = "search"
    start_hypotheses: int = 3
    search_seed: int = 0
    start_real_poses: bool = False
    start_prior_exclude: tuple[str, ...] = ()
    start_race_s: float = 0.5
    fit_bone_lengths: bool = True
    bone_fit: str = "blobs"
    em_cell_m: float = 0.0
    blobs: str = "blobs.yaml"
    floor_contact: bool = False
    floor_z_m: float | None = None
    ghost_weight: float = 0.0
    ghost_max_cameras: int = 6
    ghost_inside_scale: float = 1.15
    ghost_cover_scale: float = 1.2
    ghost_self_scale: float = 1.3
    hold_lost_feet: float = 2.0
    hold_min_confidence: float = 0.3
    hold_max_step_m: float = 0.02
    lost_hand_frames: int = 0
    rigid_trunk: bool = True
    functional_hips: float = 5.0
    functional_hips_min_cameras: int = 7

    def __post_init__(self) -> None:
        if self.refinements < 1 or self.lost_frames < 1 or self.init_passes < 1:
            raise InputError("TrackerConfig: refinements, lost_frames and init_passes must be >= 1")
        if self.functional_hips_min_cameras < 0:
            raise InputError(f"TrackerConfig.functional_hips_min_cameras must be >= 0, got "
                             f"{self.functional_hips_min_cameras}")
        if self.start not in STARTS:
            raise InputError(f"TrackerConfig.start must be one of {', '.join(STARTS)}, got {self.start!r}")
        if not self.start_race_s >= 0:
            raise InputError(f"TrackerConfig.start_race_s must be >= 0 s, got {self.start_race_s}")
        if self.start_hypotheses < 1:
            raise InputError(f"TrackerConfig.start_hypotheses must be >= 1, got {self.start_hypotheses}")
        if self.bone_fit not in BONE_FITS:
            raise InputError(f"TrackerConfig.bone_fit must be one of {', '.join(BONE_FITS)}, got {self.bone_fit!r}")
        if isinstance(self.lost_hand_frames, bool) or not isinstance(self.lost_hand_frames, int) or \
                self.lost_hand_frames < 0:
            raise InputError(f"TrackerConfig.lost_hand_frames must be a whole number of frames >= 0 (0: off), got "
                             f"{self.lost_hand_frames!r}")
        if self.ghost_max_cameras < 0:
            raise InputError(f"TrackerConfig.ghost_max_cameras must be >= 0, got {self.ghost_max_cameras}")
        if not 0.0 <= self.ghost_weight <= 1.0:
            raise InputError(f"TrackerConfig.ghost_weight must be in [0, 1], got {self.ghost_weight}")
        for name in ("ghost_inside_scale", "ghost_cover_scale"):
            if not getattr(self, name) > 0:
                raise InputError(f"TrackerConfig.{name} must be > 0, got {getattr(self, name)}")
        if not (self.ghost_self_scale >= 0 and math.isfinite(self.ghost_self_scale)):
            raise InputError(f"TrackerConfig.ghost_self_scale must be >= 0 and finite (0: off), got "
                             f"{self.ghost_self_scale}")
        if not (self.hold_lost_feet >= 0 and math.isfinite(self.hold_lost_feet)):
            raise InputError(f"TrackerConfig.hold_lost_feet must be >= 0 and finite (0: off), got "
                             f"{self.hold_lost_feet}")
        if not 0.0 <= self.hold_min_confidence <= 1.0:
            raise InputError(f"TrackerConfig.hold_min_confidence must be in [0, 1], got {self.hold_min_confidence}")
        if not self.hold_max_step_m > 0:
            raise InputError(f"TrackerConfig.hold_max_step_m must be > 0, got {self.hold_max_step_m}")
        if not 0.0 <= self.velocity <= 1.0:
            raise InputError(f"TrackerConfig.velocity must be in [0, 1], got {self.velocity}")
        if not (self.velocity_fps >= 0 and math.isfinite(self.velocity_fps)):
            raise InputError(f"TrackerConfig.velocity_fps must be >= 0 and finite (0: velocity at every rate), got "
                             f"{self.velocity_fps}")
        if not (self.functional_hips >= 0 and math.isfinite(self.functional_hips)):
            raise InputError(f"TrackerConfig.functional_hips must be >= 0 and finite (0: off), got "
                             f"{self.functional_hips}")

    @classmethod
    def from_dict(cls, doc: dict[str, Any], source: str = "<config>") -> TrackerConfig:
        """Build from a mapping (the YAML file's ``tracker`` section), naming unknown keys."""
        kw = config_section(cls, doc, source, "tracker")
        try:
            if "em" in kw:
                kw["em"] = EMConfig(**kw["em"])
            if "ccd" in kw:
                kw["ccd"] = CCDConfig(**kw["ccd"])
            if "start_prior_exclude" in kw:
                kw["start_prior_exclude"] = tuple(kw["start_prior_exclude"])
            return cls(**kw)
        except (TypeError, InputError) as exc:
            raise InputError(f"{source}: {exc}") from None


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


@dataclass(frozen=True)
class _BoneFitProblem:
    """One frame's bone fit (:meth:`MarkerlessTracker._bone_fit_problem`): the blobs' ellipsoids affine in the
    parameters (the bone groups' relative changes, the neck's shift in NECK_STEP_M, a root shift in m), the voxels'
    weights, the ridge's weights and target (per parameter) and the blobs at the pose (EM's start)."""

    model: ShapeModel
    weights: torch.Tensor
    ridge_w: torch.Tensor
    target: torch.Tensor
    start: Blobs


@dataclass(frozen=True)
class FrameResult:
    """One tracked frame.

    Attributes:
        angles: (D,) state vector. output_points: (22, 3) the skeleton's output points (``output_names``).
        confidence: (22,) 0..1 per output point. valid: whether the frame was tracked.
        residual_m: mean goal-to-joint distance after IK. explained: fraction of voxel weight in blobs.
        reinitialised: the tracker re-initialised on this frame. blobs: the fitted blobs (None if invalid).
        bone_frames: (nb, 4, 4) of the solved pose.
        feet: the solved pose's ankle and toe positions (2, 2, 3) and whether the observation gave them goals
            (2, 2) bool, for the held feet (``TrackerConfig.hold_lost_feet``); None on invalid frames.
    """

    angles: torch.Tensor
    output_points: torch.Tensor
    confidence: torch.Tensor
    valid: bool
    residual_m: float
    explained: float
    reinitialised: bool
    blobs: Blobs | None
    bone_frames: torch.Tensor
    feet: tuple[torch.Tensor, torch.Tensor] | None = None


@dataclass
class _Race:
    """A start race in progress: the twin tracker (started turned round), the frames left, each side's scores and
    the twin's results with the body version each was tracked in."""

    twin: MarkerlessTracker
    frames_left: int
    origin: torch.Tensor  # the start's output points relative to its pelvis, for START_RACE_MOVED_M
    fits: list[tuple[float, float, float, float]] = field(default_factory=list)  # scores, then fit costs
    results: list[tuple[FrameResult, int]] = field(default_factory=list)
    moved_at: int | None = None  # the index in fits of the first frame where the body had moved


def with_hips_raised(skeleton: Skeleton, dz_m: float) -> Skeleton:
    """The body with its hips ``dz_m`` higher on the trunk (``functional_hips``): the pelvis' origin, which the
    hips sit on, moved up by ``dz_m`` along its z axis, the spine's joint on it down as much and the thighs
    ``dz_m`` longer. A state whose root is moved up as much (:meth:`MarkerlessTracker.restate`) puts the trunk,
    arms and head where the body's old state put them, and the knees and feet too where the thighs hang straight.
    The blobs follow the bones: the thigh blobs grow with the thighs, and the pelvis blob, whose extent along the
    trunk is a share of the pelvis' length (to the spine's joint), shrinks with it; the pelvis keeps at least a
    fifth of its length (FUNCTIONAL_HIPS_MAX_M)."""
    spine = skeleton.joint_origin(SPINE_JOINT)
    lengths = dict(zip(skeleton.bone_names, skeleton.bone_lengths.tolist()))
    return skeleton.with_joint_origins({SPINE_JOINT: (spine[0], spine[1], spine[2] - dz_m)}).with_bone_lengths(
        {b: lengths[b] + dz_m for b in THIGH_BLOBS})


class MarkerlessTracker:
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
        self.height_m: float | None = None
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
        self._revised: list[tuple[FrameResult, int]] = []  # a won race's frames, for take_revised
        self._twin = False  # this tracker races another's start (it starts no race of its own)

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
        self.subject = Subject(skeleton, self.config.ccd, self.blob_specs).to(skeleton.lower.device)
        self.height_m = skeleton.height()

    def initialize_from_pose(self, angles: torch.Tensor, height_m: float | None = None, *,
                             skeleton: Skeleton | None = None, floor_z_m: float | None = None) -> None:
        """Start from a known state vector ``angles (D,)`` of a subject ``height_m`` tall (the body model
        scaled to it) or with a given ``skeleton`` (e.g. a previous run's fitted one); give one of the two.
        The floor (for ``floor_contact``) is ``floor_z_m`` when given (e.g. the floor an earlier run measured),
        else the pose's lower sole; the config's ``floor_z_m`` overrides both."""
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
        self.lost = 0
        self.hands_off = [0, 0]
        self._remember_feet()
        if floor_z_m is None:
            floor_z_m = float(sole_heights(self.feet_seen, self.subject.ankle_height).min())
        self._set_floor(floor_z_m)

    def _set_floor(self, soles_z: float) -> None:
        self.floor_z = soles_z if self.config.floor_z_m is None else float(self.config.floor_z_m)

    def _starfish_top_ratio(self) -> float:
        """Head-top height in the starfish pose over standing height (the spread legs lower the body)."""
        g = self.generic
        top = g.forward_frames(g.starfish_angles()[None])[0, g.frame_index(["head_top"])[0], 2, 3]
        return float(top) / g.height()

    def reset(self) -> None:
        """Back to uninitialised: the next frame with a person in it starts the track again (the automatic start);
        the refusals of earlier starts are forgotten."""
        self._clear()
        self.start_refusals = []

    def _clear(self) -> None:
        self._race, self._revised = None, []
        self.subject = self.angles = self.previous = self.colour = self.height_m = self.floor_z = None
        self.hips, self.hip_shifts, self.bodies, self.hip_estimate = None, [], [], None
        self.feet_seen = self.feet_still = None
        self.lost = 0
        self.hands_off = [0, 0]

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
            self._start_race(obs, res)
        return res

    def _race_frames(self, seconds: float | None = None) -> int:
        seconds = self.config.start_race_s if seconds is None else seconds
        return max(1, round(seconds * (self.frame_rate or self.config.velocity_fps or 30.0)))

    @property
    def racing(self) -> bool:
        """A start race is in progress (``TrackerConfig.start_race_s``): :meth:`take_revised` may yet revise the
        frames since the start."""
        return self._race is not None

    def _fork(self) -> MarkerlessTracker:
        """A copy of this tracker's state that tracks on its own (the models and settings shared, read-only)."""
        shared = (self.generic, self.config, self.blob_specs, self.subject)
        return copy.deepcopy(self, memo={id(x): x for x in shared})

    def _start_race(self, obs: VoxelObservation, res: FrameResult) -> None:
        """``start_race_s``: the twin started from this start turned round, finished on ``obs`` as a start is."""
        from torchtrack.tracking.search import turned_round

        twin = self._fork()
        twin._twin = True
        twin.angles = twin.previous = turned_round(self.subject.skeleton, res.angles)
        twin.colour = None
        for _ in range(self.config.init_passes):
            r = twin._track(obs, learn_colour=False, max_rot=math.radians(45), predicted=False, hold=False)
            twin.angles = twin.previous = r.angles
        r = twin._learn_colour(obs)
        twin._remember_feet()
        wait = max(self._race_frames(), self._race_frames(START_RACE_WAIT_S))
        self._race = _Race(twin, wait, res.output_points - res.output_points[:1])
        self._race_step(obs, res, r, twin.body_version)

    def _race_step(self, obs: VoxelObservation | None, res: FrameResult, twin_res: FrameResult, version: int
                   ) -> None:
        """One frame of the race: both scored on ``obs`` (None: not observed), the twin's result kept with the body
        version it was tracked in; ``start_race_s`` counted from the frame where the body moved
        (``START_RACE_MOVED_M``), and the race decided at its end on the frames from there."""
        from torchtrack.tracking.search import score_states

        race = self._race
        race.results.append((twin_res, version))
        if obs is not None and math.isfinite(res.residual_m) and math.isfinite(twin_res.residual_m):  # both fitted
            both = torch.stack([res.angles, twin_res.angles]).to(self.subject.skeleton.lower)
            score = score_states(obs, self.subject.skeleton, self.subject.blobs, both)[0]
            race.fits.append((float(score[0]), float(score[1]), self._fit_cost(res), self._fit_cost(twin_res)))
            if race.moved_at is None:
                shift = (res.output_points - res.output_points[:1] - race.origin).norm(dim=-1).max()
                if float(shift) > START_RACE_MOVED_M:
                    race.moved_at = len(race.fits) - 1
                    race.frames_left = self._race_frames()
        race.frames_left -= 1
        if race.frames_left > 0:
            return
        self._race = None
        fits = race.fits[race.moved_at or 0:]
        if not fits:  # nothing both fitted during the race: the search's start stays
            return
        own, other, own_cost, other_cost = (sum(col) / len(fits) for col in zip(*fits))
        log.debug("start race over %d frames (decided on the last %d, the body moved on frame %s): the search's start "
                  "scores %.3f, turned round %.3f; fit cost %.1f / %.1f mm", len(race.results), len(fits),
                  race.moved_at, own, other, 1e3 * own_cost, 1e3 * other_cost)
        if other_cost < own_cost and other >= own - START_RACE_MARGIN and (
                other > own + START_RACE_MARGIN or other_cost < START_RACE_COST_RATIO * own_cost):
            revised = race.results
            self.__dict__.update(race.twin.__dict__)  # this tracker goes on as the twin
            self._race, self._revised, self._twin = None, revised, False

    def take_revised(self) -> list[tuple[FrameResult, int]]:
        """The results that replace the last ``len(...)`` frames this tracker returned, each with the body version
        it was tracked in (:attr:`body_version`), and forgets them: a start race the start turned round won
        (``TrackerConfig.start_race_s``). Empty otherwise."""
        out, self._revised = self._revised, []
        return out

    def _initialize(self, obs: VoxelObservation) -> FrameResult:
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

    def _finish_start(self, obs: VoxelObservation, res: FrameResult, height: float, body_m3: float, toe: float,
                      tried: tuple) -> FrameResult:
        """From a start's fit: the bone fit, the checks (the starfish's raised arms only for its start), the
        colours learnt."""
        pts = obs.points
        # the bone fit's rounds explain ghosts away: so does the fit they must improve on
        for _ in range(max(2, self.config.init_passes // 3) if self._explains_ghosts(obs) else 0):
            res = self._track(obs, learn_colour=False, max_rot=math.radians(45))
            self.angles = self.previous = res.angles
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
            for _ in range(max(2, self.config.init_passes // 3)):
                res = self._track(obs, learn_colour=False, max_rot=math.radians(45))
                self.angles = self.previous = res.angles
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
        return self._learn_colour(obs)

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

    def _fit_bone_lengths(self, obs: VoxelObservation, res: FrameResult, start_body: Skeleton,
                          ridge: float | None = None) -> tuple[Skeleton, float]:
        """Bone lengths fitted to a frame's voxels at its solved pose (``TrackerConfig.bone_fit``).

        At fixed joint angles every blob's centre is affine in the bones' scale factors (a bone's length scales
        its blobs' offsets and every joint origin it carries), so the effect of each bone group (left and right
        tied) is one finite difference, as is the neck's height on the torso (NECK_JOINT; the torso's scale
        moves it and the shoulders, the shift the neck alone); each blob's semi-axis along its bone is affine in
        them too (read off the same edited blob models). Solves for the group scales, the neck shift and a root
        shift, with a ridge towards the ``start_body`` skeleton's lengths and neck (the fit's first body; ``ridge``,
        by default BONE_FIT_RIDGE or SHAPE_FIT_RIDGE), by linear least squares on the means and lengths of blobs
        that EM fitted without priors (``"blobs"``) or by fitting the union of the ellipsoids to the voxels
        (``"shape"``, :func:`~torchtrack.blobs.shape.fit_shape`); returns the new skeleton and the largest relative
        change. ``obs``: the frame's voxels split to ``BONE_FIT_VOXEL_M`` (the caller splits them once for all
        rounds).
        """
        shape = self.config.bone_fit == "shape"
        ridge = (SHAPE_FIT_RIDGE if shape else BONE_FIT_RIDGE) if ridge is None else ridge
        p = self._bone_fit_problem(obs, res.angles, start_body, ridge)
        if shape:
            x, _ = fit_shape(p.model, obs.points, obs.sizes, p.weights, p.ridge_w, p.target,
                             self._shape_starts(p.target.device), obs.volume_m)
        else:
            K, G = p.model.centres.shape[0], len(BONE_GROUPS) + 1
            base, R_wb = p.model.centres.to(p.start.mean.dtype), p.model.R_world
            raw = dataclasses.replace(self.config.em, position_prior=0.0, shape_prior=0.0, min_fill=0.05)
            fitted, _ = fit_blobs(obs.points, p.weights, obs.sizes, None, p.start, raw)
            r_pos = (fitted.mean - base).reshape(3 * K)
            inside = self._inside_volume(obs, p.start)
            w_blob = (fitted.active & inside).to(base.dtype) * fitted.fill.clamp(0, 1)  # (K,)
            # sizes along the bone
            along = R_wb[:, :, 0].to(base)  # (K, 3)
            semi_fit = (5.0 * torch.einsum("ki,kij,kj->k", along, fitted.cov, along)).clamp(min=0).sqrt()
            A = torch.cat([p.model.d_centres.reshape(3 * K, G + 3), p.model.d_along])
            r = torch.cat([r_pos, semi_fit - p.model.semi_axes[:, 0].to(base)]).double()
            w = torch.cat([w_blob.repeat_interleave(3), w_blob]).double()  # the variance along the bone axis is
            # defined for round blobs too
            rhs = A.T @ (w * r) + p.ridge_w * p.target
            x = torch.linalg.solve(A.T @ (w[:, None] * A) + torch.diag(p.ridge_w)
                                   + 1e-9 * torch.eye(G + 3, dtype=A.dtype, device=A.device), rhs)
        return self._apply_bone_fit(x, res.angles.device)

    def refit_bone_lengths(self, observations: Sequence[VoxelObservation], angles: torch.Tensor,
                           start_body: Skeleton | None = None, progress: str | None = None) -> tuple[Skeleton, float]:
        """The subject's bone lengths fitted to several frames' voxels at once, each at its tracked pose: the
        shape fit (:func:`~torchtrack.blobs.shape.fit_shape_frames`) with the bone groups' scales and the neck's
        shift shared and a root shift per frame. A pose that bends a joint shows where it is, which the one
        starfish frame of the initialisation leaves to the union's width: after a first track, the body refitted
        on its frames and tracked again (:func:`~torchtrack.tracking.body_refit.track_with_body_refit`).

        Args:
            observations: F frames' voxels (split to ``BONE_FIT_VOXEL_M`` here). angles: (F, D) their poses under
            the current subject. start_body: the ridge's target (default: the current subject's skeleton).
            progress: the label of the shape fit's progress bar (None: no bar).

        Returns:
            the new skeleton and its largest relative change.
        """
        if self.subject is None:
            raise InputError("refit_bone_lengths: the tracker has no subject yet (initialise it first)")
        check_shape(angles, (len(observations), self.generic.num_dofs), "angles")
        if not observations:
            raise InputError("refit_bone_lengths: no frames")
        start_body = self.subject.skeleton if start_body is None else start_body
        frames = []
        colour, self.colour = self.colour, None  # every blob may explain a ghost's ray, as at initialisation
        try:
            for obs, a in zip(observations, angles):
                obs = obs.split(BONE_FIT_VOXEL_M)
                p = self._bone_fit_problem(obs, a.to(self.subject.blobs.semi_axes), start_body, SHAPE_FIT_RIDGE)
                frames.append(ShapeFrame(p.model, obs.points, obs.sizes, p.weights, obs.volume_m))
        finally:
            self.colour = colour
        # the ridge depends only on the current and the start body, the same for every frame: the last frame's
        shared, _, _ = fit_shape_frames(frames, p.ridge_w[:-3], p.target[:-3],
                                        [x0[:-3] for x0 in self._shape_starts(p.target.device)], local=3,
                                        progress=progress)
        return self._apply_bone_fit(torch.cat([shared, shared.new_zeros(3)]), angles.device)

    @staticmethod
    def _shape_starts(device: torch.device) -> list[torch.Tensor]:
        """The shape fit's starts (SHAPE_FIT_STARTS) as parameter vectors (the groups', the neck's, the root's)."""
        G = len(BONE_GROUPS) + 1
        head = BONE_GROUPS.index(("head",))
        starts = []
        for neck_x, head_x in SHAPE_FIT_STARTS:
            x0 = torch.zeros(G + 3, dtype=torch.float64, device=device)
            x0[G - 1], x0[head] = neck_x, head_x
            starts.append(x0)
        return starts

    def _bone_fit_problem(self, obs: VoxelObservation, angles: torch.Tensor, start_body: Skeleton, ridge: float
                          ) -> _BoneFitProblem:
        """The bone fit's affine model of the blobs at the pose ``angles (D,)`` (:meth:`_fit_bone_lengths`), the
        voxels' ghost weights and the ridge towards ``start_body``."""
        sub = self.subject
        skel = sub.skeleton
        angles = angles[None]
        specs, ref = self.blob_specs
        fk = skel.forward(angles)
        base, base_cov = sub.blobs.gaussians(fk.bone_frames)
        base, base_cov = base[0], base_cov[0]  # (K, 3), (K, 3, 3)
        R_wb = sub.blobs.ellipsoids(fk.bone_frames)[1][0]  # (K, 3, 3) the blobs' axes, the first along the bone
        start = prior_blobs(base, base_cov)
        weights = self._ghost_weights(obs, start)  # (N,)
        lengths = dict(zip(skel.bone_names, skel.bone_lengths.tolist()))
        K = base.shape[0]
        neck = skel.joint_origin(NECK_JOINT)
        semi_now = sub.blobs.semi_axes[:, 0].to(base)  # (K,) each blob's semi-axis along its bone
        cols, size_cols = [], []
        for edited in [skel.with_bone_lengths({b: 2.0 * lengths[b] for b in group}) for group in BONE_GROUPS] + [
                skel.with_joints_raised({NECK_JOINT: NECK_STEP_M})]:
            edited = edited.to(angles.device)
            blobs2 = BlobModel(edited, specs, ref).to(angles.device)
            cols.append(blobs2.gaussians(edited.forward(angles).bone_frames)[0][0] - base)  # (K, 3) per step
            size_cols.append(blobs2.semi_axes[:, 0].to(base) - semi_now)  # (K,)
        eye = torch.eye(3, dtype=base.dtype, device=base.device).expand(K, 3, 3)
        d_centres = torch.cat([torch.stack(cols, -1), eye], -1).double()  # (K, 3, G + 3); the root shift: eye
        d_along = torch.cat([torch.stack(size_cols, -1), base.new_zeros(K, 3)], -1).double()  # (K, G + 3)
        # the ridge: ridge * (c_g (1 + x_g) - 1)^2 per group, c_g its current length over the start's (a relative
        # change from the start). The torso's length is the neck's height on it, which the neck's shifts move too:
        # so the neck's height is what is pulled back, and the neck's shift then has nothing to pull back to (its
        # target is 0, a damping towards this round's body), which leaves the shoulders' height to the voxels
        start_len = dict(zip(start_body.bone_names, start_body.bone_lengths.tolist()))
        c = torch.tensor([lengths[group[0]] / start_len[group[0]] for group in BONE_GROUPS], dtype=torch.float64)
        start_neck_z = start_body.joint_origin(NECK_JOINT)[2] * float(c[BONE_GROUPS.index(("torso",))])
        ridge_w = (ridge * torch.cat([c * c, c.new_ones(1), c.new_zeros(3)])).to(d_centres)  # (G + 3,) root: none
        target = torch.cat([1.0 / c - 1.0, c.new_tensor([(start_neck_z - neck[2]) / NECK_STEP_M]),
                            c.new_zeros(3)]).to(d_centres)
        model = ShapeModel(base.double(), R_wb.double(), sub.blobs.semi_axes.to(base).double(), d_centres, d_along)
        return _BoneFitProblem(model, weights, ridge_w, target, start)

    def _apply_bone_fit(self, x: torch.Tensor, device: torch.device) -> tuple[Skeleton, float]:
        """The bone fit's parameters (the groups' relative changes, the neck's shift in NECK_STEP_M, ...) -> the
        subject's skeleton with them and the largest relative change."""
        skel = self.subject.skeleton
        G = len(BONE_GROUPS) + 1
        lengths = dict(zip(skel.bone_names, skel.bone_lengths.tolist()))
        neck = skel.joint_origin(NECK_JOINT)
        scale = (1.0 + x[:G - 1]).clamp(0.6, 1.6)
        new = {b: lengths[b] * float(scale[g]) for g, group in enumerate(BONE_GROUPS) for b in group}
        fitted_skel = skel.with_bone_lengths(new)
        shift = float(x[G - 1].clamp(-1.0, 1.0)) * NECK_STEP_M
        fitted_skel = fitted_skel.with_joints_raised({NECK_JOINT: shift})  # on the neck the torso's scale moved
        change = max(float((scale - 1).abs().max()), abs(shift) / max(neck[2], 1e-6))
        return fitted_skel.to(device), change

    # ------------------------------------------------------------------------------------------ tracking
    def _remember_feet(self) -> None:
        """The feet of the current pose as last observed and still (at initialisation)."""
        sub = self.subject
        self.feet_seen = sub.skeleton.forward(self.angles[None]).joints[0, sub.feet]  # (2, 2, 3)
        self.feet_still = torch.ones(self.feet_seen.shape[:2], dtype=torch.bool, device=self.feet_seen.device)

    def _update_feet(self, res: FrameResult) -> None:
        """After an accepted frame: each foot joint the observation gave a goal is remembered where the solved
        pose put it, and counts as still when it moved under ``hold_max_step_m`` since it was last seen, however
        many frames ago (a foot that comes back elsewhere after a gap is not held until it is seen still)."""
        if self.feet_seen is None or res.feet is None:
            return
        pos, seen = res.feet
        step = (pos - self.feet_seen).norm(dim=-1)  # (2, 2) m since it was last seen, however long ago
        self.feet_still = torch.where(seen, step < self.config.hold_max_step_m, self.feet_still)
        self.feet_seen = torch.where(seen[..., None], pos, self.feet_seen)

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

    def _results(self, st: Stepped) -> list[FrameResult]:
        """The step's batch as one :class:`FrameResult` per row (one wait for the host)."""
        residual, explained = st.residual_m.tolist(), st.explained.tolist()
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

    def _fit_many(self, obs: VoxelObservation, starts: torch.Tensor, passes: int, max_rot: float
                  ) -> list[FrameResult]:
        """Each of H states ``starts (H, D)`` fitted to ``obs`` by ``passes`` rounds of :meth:`_track` without the
        prediction's trust, held feet, colours or velocity (as ``_track(obs, learn_colour=False, max_rot,
        predicted=False, hold=False)`` from each round's result), all H in one batch: the hypotheses of a
        re-acquisition. The tracker's state is not changed."""
        if self.colour is not None:
            raise InputError("_fit_many fits without colours: the tracker's colour model must be dropped first")
        batch = VoxelBatch.of([obs], self.config.ghost_max_cameras).repeat(starts.shape[0])
        state = starts
        for _ in range(passes):
            st = track_step(self.subject.stack, batch, self._step_state(state, state, 0.0), self._step_config,
                            False, max_rot, predicted=False, hold=False)
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

    def _has_person(self, obs: VoxelObservation) -> bool:
        return obs.num_observed >= self.config.min_voxels and obs.volume_m3() >= self.config.min_volume_m3

    def skip(self) -> FrameResult:
        """A frame that cannot be observed (an unreadable camera frame): not tracked, ``valid = False``; the
        next frame predicts from the last good pose without velocity."""
        self.previous = self.angles
        res = self._invalid()
        if self._race is not None:
            twin = self._race.twin
            version = twin.body_version
            self._race_step(None, res, twin.skip(), version)
        return res

    def step(self, obs: VoxelObservation) -> FrameResult:
        """Track one frame (initialising on the first frame with a person in it). A start race's end may revise
        the frames before (:meth:`take_revised`)."""
        racing = self._race is not None  # a race started by this frame's initialisation has scored it already
        res = self._step(obs)
        if racing:  # the twin races without a race of its own: its frame is its _step
            twin = self._race.twin
            version = twin.body_version
            self._race_step(obs, res, twin._step(obs), version)
        return res

    def _step(self, obs: VoxelObservation) -> FrameResult:
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
        if self.angles is not None and self.lost >= self.config.lost_frames:
            return self._reacquire(obs)
        return self.accept(obs, self._track(obs, learn_colour=True,
                                            max_rot=math.radians(self.config.max_root_rotation_deg)))

    def routine(self, obs: VoxelObservation) -> VoxelObservation | None:
        """``obs`` as the plain per-frame step takes it (merged per ``em_cell_m``) where this frame needs nothing
        more of this tracker: it is started, not lost, not racing a start, and someone is there. Else None: the
        frame goes through :meth:`step`. A driver that runs the plain step itself (several sequences in lockstep,
        :class:`~torchtrack.tracking.lockstep.Lockstep`) hands its result to :meth:`accept`."""
        if (self._race is not None or self.subject is None or self.angles is None
                or self.lost >= self.config.lost_frames or not self._has_person(obs)):
            return None
        return obs.pooled(self.config.em_cell_m) if self.config.em_cell_m > 0 else obs

    def accept(self, obs: VoxelObservation, res: FrameResult) -> FrameResult:
        """Take in the plain step's result ``res`` on ``obs`` (as :meth:`routine` gave it): a diverging frame counts
        towards re-acquisition (which it starts after ``lost_frames``), an accepted one moves the pose, the colour
        model, the held feet and the functional hips on (and may search for a lost arm)."""
        if self._diverging(res):
            self.lost += 1
            if self.lost >= self.config.lost_frames:
                return self._reacquire(obs)
            self.previous = self.angles  # keep the last good pose, without velocity
            return replace(res, valid=False)
        self.lost = 0
        res, found = self._search_lost_arms(obs, res)
        self.previous, self.angles = self.angles.clone(), res.angles
        for arm in found:  # no velocity across the search's jump (it ran off again the way it came)
            self.previous[arm] = res.angles[arm]
        self.colour = res.blobs  # the colour model follows accepted frames only
        self._update_feet(res)
        if self.hips is not None and int(obs.cameras_valid.sum()) >= self.config.functional_hips_min_cameras:
            self._learn_hips(res)
        return res

    def _search_lost_arms(self, obs: VoxelObservation, res: FrameResult) -> tuple[FrameResult, list[torch.Tensor]]:
        """``lost_hand_frames``: an accepted frame's result, or the frame tracked again with a lost arm at rest
        where that fits better (see :class:`TrackerConfig`), and the DOF indices of each arm so found. Counts each
        hand's de-activated frames since it went off or was last searched for."""
        n = self.config.lost_hand_frames
        found_arms: list[torch.Tensor] = []
        if n <= 0:
            return res, found_arms
        sub = self.subject
        again = None  # the frame tracked once more as it is: once for both arms, until a search is kept
        for i, side in enumerate(("l", "r")):
            k = sub.blobs.names.index(f"{side}_hand")
            self.hands_off[i] = 0 if bool(res.blobs.active[k]) else self.hands_off[i] + 1
            if self.hands_off[i] < n:
                continue
            self.hands_off[i] = 0  # the next search n frames on: a hand no view shows costs 2 passes per n frames
            hanging = res.angles.clone()
            hanging[sub.arm_dofs[i]] = sub.arm_rest[i]
            # both from this frame's solution, one more pass each: a second pass alone lowers the cost (the rest of
            # the body fits again), so the search is measured against the frame tracked again as it is
            if again is None:
                again = self._track_again(obs, res.angles)
            trial = self._track_again(obs, sub.skeleton.clamp(hanging[None])[0])
            cost, trial_cost = self._fit_cost(again), self._fit_cost(trial)
            found = trial_cost < cost and not self._diverging(trial)
            log.debug("the %s hand off for %d frames: the arm searched from hanging fits at %.1f mm against %.1f: %s",
                      side, n, 1e3 * trial_cost, 1e3 * cost, "kept" if found else "refused")
            if found:
                res, again = trial, None
                found_arms.append(sub.arm_dofs[i])
        return res, found_arms

    def _track_again(self, obs: VoxelObservation, angles: torch.Tensor) -> FrameResult:
        """The frame tracked once more from ``angles``, without velocity; the tracker's pose is left as it was."""
        kept = self.angles, self.previous
        self.angles = self.previous = angles
        try:
            return self._track(obs, learn_colour=True, max_rot=math.radians(self.config.max_root_rotation_deg))
        finally:
            self.angles, self.previous = kept

    # ------------------------------------------------------------------------------------ functional hips
    @property
    def body_version(self) -> int:
        """How many times the subject's body has been changed since initialisation (``functional_hips``)."""
        return len(self.hip_shifts)

    def _start_hips(self, learn: bool) -> None:
        self.hip_shifts, self.bodies, self.hip_estimate = [], [], None
        self.hips = AxisPivot(2, device=self.subject.skeleton.lower.device) if (
            learn and self.config.functional_hips > 0) else None

    def _learn_hips(self, res: FrameResult) -> None:
        """Add the frame's thigh axes; once both thighs' information reaches ``functional_hips``, move the hips
        to their functional centres (:mod:`torchtrack.tracking.functional`) and stop learning."""
        sub = self.subject
        k = [sub.blobs.names.index(n) for n in THIGH_BLOBS]
        blobs = res.blobs
        weights = blobs.active[k].to(blobs.fill) * blobs.fill[k].clamp(0, 1)
        self.hips.add(res.bone_frames[sub.skeleton.bone_names.index("pelvis")], blobs.mean[k], blobs.cov[k],
                      weights)
        if not bool((self.hips.information() >= self.config.functional_hips).all()):
            return
        skel = sub.skeleton
        hips_z = torch.tensor([skel.joint_origin(j)[2] for j in HIP_JOINTS], dtype=self.hips.rhs.dtype)
        above = self.hips.centres().cpu()[:, 2] - hips_z  # (2,)
        self.hip_estimate = (above, self.hips.information().cpu())
        dz = float(above.mean())
        self.hips = None
        spine = skel.joint_origin(SPINE_JOINT)
        if not 0.0 <= dz <= FUNCTIONAL_HIPS_MAX_M or spine[2] - dz < 0.2 * spine[2]:
            log.warning("functional hips: the thighs pivot %.0f mm above the fitted hips (a move up of at most %.0f "
                        "mm is made); the body is left as fitted", 1e3 * dz, 1e3 * FUNCTIONAL_HIPS_MAX_M)
            return
        log.info("functional hips: the thighs pivot %.0f mm above the fitted hips (left %.0f, right %.0f); the hips "
                 "and the pelvis' origin are moved up, the thighs lengthened", 1e3 * dz, *(1e3 * above).tolist())
        self.move_hips(dz)

    def move_hips(self, dz_m: float) -> None:
        """Raise the subject's hips by ``dz_m`` on its trunk (:func:`with_hips_raised`; a new
        :attr:`body_version`), the tracked state re-stated in the new body (:meth:`restate`)."""
        skel = self.subject.skeleton
        self.bodies.append(skel)
        self._use(with_hips_raised(skel, dz_m).to(skel.lower.device))
        self.hip_shifts.append(float(dz_m))
        self.angles, self.previous = (None if a is None else self.restate(a[None], self.body_version - 1)[0]
                                      for a in (self.angles, self.previous))

    def restate(self, angles: torch.Tensor, version: int | torch.Tensor = 0) -> torch.Tensor:
        """State vectors of the subject's body as it was at ``version`` (:attr:`body_version`) in its current
        body (``functional_hips``): the root (the pelvis' origin) moved up along the pelvis' z axis as the hips
        were, which keeps the trunk, arms and head where they were, then CCD (the tracker's) towards the joints
        the body of that version put there but the hips, which bends the longer thighs back towards the knees
        and the feet: exactly where the thigh hangs straight under the hip, off by about dz (1 - cos flexion)
        otherwise (a longer thigh from a higher hip cannot reach a flexed knee: 1.4 cm off at 1 rad for dz 3 cm,
        3 cm at 1.6 rad). A NaN state stays NaN.

        Args:
            angles: (N, D). version: one version, or (N,) per state.
        """
        check_shape(angles, ("N", self.generic.num_dofs), "angles")
        V = self.body_version
        since = torch.tensor([sum(self.hip_shifts[v:]) for v in range(V + 1)], dtype=angles.dtype,
                             device=angles.device)  # (V + 1,) how far the hips moved since each version
        version = torch.as_tensor(version, device=angles.device).expand(angles.shape[0]).clamp(0, V)  # (N,)
        dz = since[version]  # (N,)
        names = self.generic.dof_names
        rot = root_rotation_matrix(angles[:, [names.index(n) for n in ("root_rz", "root_ry", "root_rx")]])
        out = angles.clone()
        t = [names.index(n) for n in ("root_tx", "root_ty", "root_tz")]
        out[:, t] = angles[:, t] + rot[:, :, 2] * dz[:, None]
        sub = self.subject
        goal_w = torch.tensor([0.0 if j in HIP_FRAMES else 1.0 for j in CCD_GOALS], dtype=angles.dtype,
                              device=angles.device)
        finite = torch.isfinite(angles).all(1)
        for v in range(V):
            sel = (version == v) & finite
            if bool(sel.any()):
                old = self.bodies[v].to(angles.device).forward(angles[sel]).joints[:, sub.ccd_goal_index]
                out[sel] = sub.ccd(out[sel], old, goal_w)
        return out

    @staticmethod
    def _fit_cost(res: FrameResult) -> float:
        """How badly a hypothesis fits (initialisation and re-acquisition pick the least): metres of goal
        residual plus 0.1 m per unit of voxel weight left unexplained."""
        return res.residual_m + 0.1 * (1.0 - res.explained)

    def _diverging(self, res: FrameResult) -> bool:
        return res.residual_m > self.config.lost_residual_m or res.explained < self.config.min_explained

    def _searched(self, obs: VoxelObservation) -> FrameResult | None:
        """The subject's body searched for in ``obs`` from any pose (:mod:`torchtrack.tracking.search`, its size
        fixed), the best hypothesis finished by EM/IK; None where it lies out of the observed volume."""
        from torchtrack.tracking.search import SearchConfig, search_pose

        gen = torch.Generator(device=obs.points.device).manual_seed(self.config.search_seed)
        found = search_pose(obs, self.subject.skeleton, self.subject.blobs, SearchConfig(
            scale_range=(1.0, 1.0), real_poses=self.config.start_real_poses,
            prior_exclude=self.config.start_prior_exclude), gen, n=1)
        if float(found.outside[0]) > START_MAX_OUTSIDE:
            return None
        self.angles = self.previous = found.angles[0].to(obs.points.dtype)
        res = None
        for _ in range(max(2, self.config.init_passes // 2)):
            res = self._track(obs, learn_colour=False, max_rot=math.radians(45), predicted=False, hold=False)
            self.angles = self.previous = res.angles
        return res

    def _reacquire(self, obs: VoxelObservation) -> FrameResult:
        """Re-initialise: around the last good pose (moved onto the voxels' centroid, four headings) and, at once
        and then every REACQUIRE_SEARCH_EVERY lost frames, from any pose by the start's search. Of the fits that
        do not diverge, those within REACQUIRE_SCORE_MARGIN of the best two-way score (EM/IK's residual alone
        cannot tell a body turned a quarter or half round from the right one) compete by the fit cost; the winner
        races its twin turned round as a start does (``start_race_s``). The colour model goes: the fits go without
        it and the re-acquired frame learns it afresh."""
        from torchtrack.tracking.search import score_states

        pts, w = obs.points, obs.weights
        c = (w[:, None] * pts).sum(0) / w.sum()
        skel = self.subject.skeleton
        base = self.angles.clone()
        self.colour = None  # learnt before the loss (elsewhere in the room, or from frames losing the body)
        ix, iy, irz = (skel.dof_names.index(n) for n in ("root_tx", "root_ty", "root_rz"))
        starts = base.repeat(4, 1)
        starts[:, ix], starts[:, iy] = c[0], c[1]
        starts[:, irz] = base[irz] + torch.tensor([0.0, 0.5, 1.0, -0.5], dtype=base.dtype, device=base.device) * math.pi
        fits = self._fit_many(obs, starts, max(2, self.config.init_passes // 2), math.radians(45))
        if (self.lost - self.config.lost_frames) % REACQUIRE_SEARCH_EVERY == 0:
            found = self._searched(obs)
            if found is not None:
                fits.append(found)
        held = [r for r in fits if not self._diverging(r)]
        if not held:  # keep searching from the last good pose on the next frame
            self.angles = self.previous = base
            self.lost += 1
            return replace(min(fits, key=self._fit_cost), valid=False, reinitialised=True)
        score = score_states(obs, skel, self.subject.blobs, torch.stack([r.angles for r in held]))[0]
        log.debug("re-acquisition: %d of %d fits hold, scores %s; fit costs %s mm", len(held), len(fits),
                  " ".join(f"{float(x):.3f}" for x in score), " ".join(f"{1e3 * self._fit_cost(r):.1f}" for r in held))
        close = [r for r, x in zip(held, score.tolist()) if x >= float(score.max()) - REACQUIRE_SCORE_MARGIN]
        best = min(close, key=self._fit_cost)
        self.angles = self.previous = best.angles
        self.lost = 0
        self.hands_off = [0, 0]
        if self.feet_seen is not None and best.feet is not None:  # a held foot the new pose left is let go
            far = (best.feet[0] - self.feet_seen).norm(dim=-1) > REACQUIRED_FOOT_M
            self.feet_still = self.feet_still & ~far
        best = self._learn_colour(obs)
        if (self.config.start == "search" and self.config.start_race_s > 0 and self._race is None
                and not self._twin):
            self._start_race(obs, best)
        return best
