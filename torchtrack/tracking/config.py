"""The markerless tracker's settings (:class:`TrackerConfig`; ``configs/markerless.yaml``'s ``tracker`` section)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from torchtrack.blobs.em import EMConfig
from torchtrack.checks import InputError, config_section
from torchtrack.skeleton.ik import CCDConfig

#: TrackerConfig.bone_fit's choices.
BONE_FITS = ("blobs", "shape")
#: How the first pose is found (TrackerConfig.start).
STARTS = ("search", "starfish")
#: ``floor_band_m: null``: the floor band's height (the lowest layer of the default 3 cm grid) on rigs of at least
#: FLOOR_BAND_MIN_CAMERAS cameras, off on fewer, where it cost the clean synthetic table more than a floor shadow's
#: ghost cost the stress table (docs/results.md, "Robustness", the floor band).
FLOOR_BAND_M, FLOOR_BAND_MIN_CAMERAS = 0.03, 7


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
            other pose: for recordings that open with a clear starfish, where a start in any other pose should
            be refused rather than searched for.
        start_real_poses: the search also starts from real captured poses
            (:func:`~torchtrack.tracking.poses.real_pose_prior`). Turn it on for a subject in crouched, twisted or
            reaching poses seen by 8 or more cameras, where more starts land right. Off by default: beside phantom
            volume it can take a taller body with its arms raised into the phantom, and one stress sequence
            tracked worse (docs/results.md, "Real poses in the prior").
        start_prior_exclude: the search leaves out the real captures' poses whose capture's name contains one of
            these (:func:`~torchtrack.tracking.poses.real_pose_prior`): for evaluations on the captures the prior
            was built from, which leave their subject out (scripts/eval_start.py, eval_robustness.py).
        start_limb_sweep: once a start is fitted (its pose finished by EM/IK, its bones' lengths fitted), each limb
            is swept again over the search's grid on the fitted body, the rest kept, and the best swept pose,
            finished by EM/IK, is the start where it scores higher than the start tracked again
            (:func:`~torchtrack.tracking.search.sweep_limbs`; the start race's twin, the start before the sweep
            turned round, is swept likewise for its own heading): the search's sweep ran on the template's
            proportions before EM/IK had placed the trunk, and a start often has one arm off (docs/results.md, "The
            limb sweep on the fitted body").
        start_race_s: after a searched start (and a re-acquisition, with that start), the start turned round (the
            same silhouette facing the other way, which one frame's voxels cannot tell from it:
            :func:`~torchtrack.tracking.poses.turned_round`) is tracked beside it for this long from the body's
            first move (``START_RACE_MOVED_M``), and the one whose poses fit the voxels better from that move on
            (EM/IK's fit cost lower, the mean two-way score not lower by more than ``START_RACE_MARGIN``, and one
            of the two clearly better: the score by that margin or the cost by ``START_RACE_COST_RATIO``) is
            kept, its frames replacing the other's
            (:meth:`MarkerlessTracker.take_revised`): a body's motion shows which way it faces, as knees and elbows
            bend one way only (0: off).
        settle_back_s: after a start or a re-acquisition, once the track has held this long (and any start race is
            decided), the frames since are tracked again backwards from there and the two tracks spliced once,
            where their summed fit cost is least (:mod:`~torchtrack.tracking.settle`; 0: off; a sequence that ends
            sooner is tracked back from its last frame, :meth:`MarkerlessTracker.finish`): the first frames after a
            re-acquisition at the volume's edge, tracked from a guess, are the track's worst
            (docs/results.md, "Robustness", the subject who leaves).
        recheck_s: a re-acquisition is made where the body comes back, often at the observed volume's edge:
            partly out of it, where the search does not look (its fits then come from the last good pose alone,
            facing the way the subject left), or seen by few cameras, where the search's answer is a guess too. For
            up to this long after its start race, the first frame whose tracked body lies within the volume (as the
            search asks, ``START_MAX_OUTSIDE``) runs the search once more, and its answer replaces the track (as a
            re-acquisition, with its race) where its two-way score is higher by more than
            ``REACQUIRE_SCORE_MARGIN`` and its fit cost no higher (0: off; docs/results.md, "The re-acquisition's
            check").
        image_hold_s: a body that walks out of the observed volume (where fewer cameras see it than the grid asks
            for, ``observation.min_views``), whose voxels are gone or cut off, is tracked for up to this long in
            the images of the cameras that still show it (:func:`~torchtrack.tracking.search.search_near_in_images`
            from the prediction, where at least ``image_hold_min_cameras`` cameras show it), where it would be
            invalid and then re-acquired; the count starts again once the voxels accept a frame. After a
            re-acquisition, the invalid frames just before it (up to ``image_hold_s``) are tracked back from it in
            their images likewise, while the cameras show the body. Such frames' confidence is
            ``image_hold_confidence``. Needs ``observation.silhouettes`` (0: off).
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
        em_cell_m: merge the voxels per cell of this size before EM (0: off). Turn it on for fine hulls, whose EM
            cost grows with the voxel count while the blobs need no such detail, as ``markerless_fast.yaml`` does
            (its speed on the fine 4-camera hull: docs/results.md, "Speed").
        blobs: blob config file (``configs/`` name or path).
        floor_contact: keep the lowest foot on the floor (Caillette §4.2: at least one part of the body touches
            the floor; :func:`~torchtrack.tracking.goals.floor_contact`). Turn it on for a subject who never
            leaves the floor and whose feet the voxels lose (a stance held so still that the background takes
            the lower legs; tests/test_markerless.py builds such a case). Off by default: wrong for jumps and
            running, no better on the synthetic table and worse on the Pose2Sim demo (docs/results.md, "Floor
            contact").
        floor_z_m: the floor's height for the contact (m); None: the soles' height at initialisation (the
            lowest voxels of the starfish frame, or the initial pose's lower toe site).
        floor_band_m: the voxels whose centres lie less than this above the observed volume's floor get no weight
            in EM/IK and the bone fits once the start has chosen its pose (:meth:`~torchtrack.tracking.voxels.
            VoxelObservation.without_floor_band`): a floor shadow that the background takes for foreground is a
            thin ghost volume there, which pulls the feet into the floor whatever the clothes' colours; the feet
            keep their voxels above it. The start's choice of pose and the start race keep every voxel (the toes
            tell a body's front from its back). None (the default): FLOOR_BAND_M on rigs of at least
            FLOOR_BAND_MIN_CAMERAS cameras, off on fewer; 0: off (docs/results.md, "Robustness", the floor band).
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
    start_limb_sweep: bool = True
    start_race_s: float = 0.5
    settle_back_s: float = 1.0
    recheck_s: float = 2.0
    image_hold_s: float = 0.0
    image_hold_min_cameras: int = 3
    image_hold_confidence: float = 0.5
    fit_bone_lengths: bool = True
    bone_fit: str = "blobs"
    em_cell_m: float = 0.0
    blobs: str = "blobs.yaml"
    floor_contact: bool = False
    floor_z_m: float | None = None
    floor_band_m: float | None = None
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
        if not 0 <= self.settle_back_s < math.inf:
            raise InputError(f"TrackerConfig.settle_back_s must be a number of seconds >= 0, got "
                             f"{self.settle_back_s}")
        if not 0 <= self.recheck_s < math.inf:
            raise InputError(f"TrackerConfig.recheck_s must be a number of seconds >= 0, got {self.recheck_s}")
        if not 0 <= self.image_hold_s < math.inf:
            raise InputError(f"TrackerConfig.image_hold_s must be a number of seconds >= 0, got {self.image_hold_s}")
        if isinstance(self.image_hold_min_cameras, bool) or not isinstance(self.image_hold_min_cameras, int) or \
                self.image_hold_min_cameras < 2:
            raise InputError(f"TrackerConfig.image_hold_min_cameras must be a whole number of cameras >= 2, got "
                             f"{self.image_hold_min_cameras!r}")
        if not 0 <= self.image_hold_confidence <= 1:
            raise InputError(f"TrackerConfig.image_hold_confidence must be within [0, 1], got "
                             f"{self.image_hold_confidence}")
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
        for name in ("ghost_self_scale", "hold_lost_feet", "functional_hips", "velocity_fps"):  # 0: off
            if not (getattr(self, name) >= 0 and math.isfinite(getattr(self, name))):
                raise InputError(f"TrackerConfig.{name} must be >= 0 and finite (0: off), got {getattr(self, name)}")
        if self.floor_band_m is not None and not (self.floor_band_m >= 0 and math.isfinite(self.floor_band_m)):
            raise InputError(f"TrackerConfig.floor_band_m must be >= 0 and finite (0: off) or null, got "
                             f"{self.floor_band_m}")
        if not 0.0 <= self.hold_min_confidence <= 1.0:
            raise InputError(f"TrackerConfig.hold_min_confidence must be in [0, 1], got {self.hold_min_confidence}")
        if not self.hold_max_step_m > 0:
            raise InputError(f"TrackerConfig.hold_max_step_m must be > 0, got {self.hold_max_step_m}")
        if not 0.0 <= self.velocity <= 1.0:
            raise InputError(f"TrackerConfig.velocity must be in [0, 1], got {self.velocity}")

    def floor_band(self, num_cameras: int) -> float:
        """The floor band's height (m) on a rig of ``num_cameras`` cameras (``floor_band_m``; 0: off)."""
        if self.floor_band_m is not None:
            return float(self.floor_band_m)
        return FLOOR_BAND_M if num_cameras >= FLOOR_BAND_MIN_CAMERAS else 0.0

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
