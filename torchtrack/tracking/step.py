"""The tracker's per-frame step as a function of a batch: B frames (sequences in lockstep, or hypotheses of one
frame), each with its own subject, voxels and state, advanced by one set of tensor operations.

One step (de Bem §III, Caillette §4; :mod:`torchtrack.tracking.markerless` tells the whole method):

1. predict each pose (damped constant velocity of the state vector) and regenerate its blobs (eq. 17-18), EM's
   start and prior, with the colour model each sequence has learnt;
2. where the prediction is trusted and the rig has few cameras, lower the EM weight of the ghost voxels the
   predicted body explains in every view (:mod:`torchtrack.tracking.ghosts`); EM of the blobs on the voxels
   (:func:`~torchtrack.blobs.em.fit_blobs` over padded voxel sets); a blob whose predicted ellipsoid lies more than
   ``MAX_OUTSIDE`` out of the observed volume gives no goals;
3. joint goals from the blobs, the root as the bounded Kabsch fit of the trunk goals (the trunk held straight
   with ``rigid_trunk``), then CCD of the spine and limbs; repeated ``refinements`` times;
4. the fit's measures: goal residual, share of the voxels' weight the blobs explain, each joint's confidence.

What to do with each result (accept it, count a divergence, re-acquire) is the driver's
(:class:`~torchtrack.tracking.markerless.MarkerlessTracker`, :mod:`torchtrack.tracking.lockstep`). Nothing here
reads files or logs, nor waits for a value from a GPU: EM and the ghost test mask rows rather than select them
there (on the CPU, where a selection costs no wait, they select), and EM asks whether a colour is known only on
the CPU. The driver then reads the results once a frame (:meth:`MarkerlessTracker._results`; the lockstep reads
its trackers' tests with them). On a GPU the root fit's SVD also waits (``torch.linalg.svd`` checks its convergence
on the host): docs/results.md, Speed, counts them.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from torchtrack.blobs.em import Blobs, EMConfig, fit_blobs
from torchtrack.blobs.model import BlobModel, blob_volumes
from torchtrack.skeleton.ik import CCDConfig, CCDSolver
from torchtrack.skeleton.model import JOINT_FRAMES, LANDMARK_FRAMES, FKResult, Skeleton
from torchtrack.skeleton.stack import SkeletonStack
from torchtrack.tracking.ghosts import ghost_voxels
from torchtrack.tracking.goals import GoalModel, feet_index, floor_contact
from torchtrack.tracking.voxels import VoxelObservation, share_outside

#: A blob with more than this share of its predicted ellipsoid out of the observed volume's sides or top gives no
#: goals (:meth:`VoxelObservation.outside`): its voxels are only the part inside, whose mean and axis pull the
#: bone inwards (a forearm coming back into the volume folded onto its upper arm, the elbow at its limit).
MAX_OUTSIDE = 0.25
#: The spine's DOFs, between the pelvis (the root) and the torso: straight (0) in the rest pose.
SPINE_DOFS: tuple[str, ...] = ("spine_flex", "spine_abd", "spine_twist")
#: lost_hand_frames: the DOFs of each arm (after its side's ``l_`` / ``r_``) put back at rest when its hand is lost.
ARM_DOFS: tuple[str, ...] = ("shoulder_flex", "shoulder_abd", "shoulder_twist", "elbow_flex", "wrist_flex")
#: Goal joints for CCD: every kinematic joint but the root (which the trunk fit places).
CCD_GOALS: tuple[str, ...] = tuple(j for j in JOINT_FRAMES if j != "pelvis")


@dataclass(frozen=True)
class StepConfig:
    """What the step needs of :class:`~torchtrack.tracking.markerless.TrackerConfig` (see it for each)."""

    em: EMConfig
    refinements: int
    rigid_trunk: bool
    floor_contact: bool
    hold_lost_feet: float
    hold_min_confidence: float
    ghost_weight: float
    ghost_max_cameras: int
    ghost_inside_scale: float
    ghost_cover_scale: float
    ghost_self_scale: float

    @classmethod
    def of(cls, config) -> StepConfig:  # noqa: ANN001 (a TrackerConfig; imported the other way round)
        return cls(**{f: getattr(config, f) for f in cls.__dataclass_fields__})


class Subject:
    """The subject-specific models: skeleton scaled to the subject, its blobs (every blob's two cross semi-axes
    times ``girth``: a slimmer or a stouter body than the template's), goals and CCD."""

    def __init__(self, skeleton: Skeleton, ccd: CCDConfig, specs: tuple[list, float], girth: float = 1.0) -> None:
        specs, ref = specs
        self.skeleton, self.girth = skeleton, girth
        self.blobs = BlobModel(skeleton, specs, ref)
        # the goals read each blob's main axis off the template's build: a stout or slim one must not turn a hand's
        # axis or the pelvis' width (the heading) into another (GoalModel's elongated and principal axes)
        self.goals = GoalModel(skeleton, self.blobs)
        self.blobs = self.blobs.widened(girth)
        self.ccd = CCDSolver(skeleton, CCD_GOALS, ccd)
        self.ccd_goal_index = torch.tensor([JOINT_FRAMES.index(j) for j in CCD_GOALS])
        self.spine_dofs = skeleton.dof_index([n for n in SPINE_DOFS if n in skeleton.dof_names])  # rigid_trunk
        self.feet = feet_index()  # (2, 2) ankle and toe site of each foot (JOINT_FRAMES indices)
        rest = skeleton.forward(skeleton.rest_angles()[None]).joints[0]  # (G, 3)
        self.ankle_height = rest[self.feet[:, 0], 2] - rest[self.feet[:, 1], 2]  # (2,) ankle above the sole
        self.body_volume_m3 = float(blob_volumes(self.blobs).sum())
        # lost_hand_frames: each arm's DOFs (left, right) and their rest values, (2, len(ARM_DOFS))
        self.arm_dofs = torch.stack([skeleton.dof_index([f"{side}_{d}" for d in ARM_DOFS]) for side in ("l", "r")])
        self.arm_rest = skeleton.rest_angles()[self.arm_dofs]
        self.output_joint = torch.tensor([JOINT_FRAMES.index(LANDMARK_FRAMES.get(n, n)) if
                                          LANDMARK_FRAMES.get(n, n) in JOINT_FRAMES else -1
                                          for n in skeleton.output_names])
        self._stack: SubjectStack | None = None

    def to(self, device: torch.device) -> Subject:
        for m in (self.skeleton, self.blobs, self.goals, self.ccd):
            m.to(device)
        self.output_joint, self.spine_dofs = self.output_joint.to(device), self.spine_dofs.to(device)
        self.ccd_goal_index = self.ccd_goal_index.to(device)
        self.feet, self.ankle_height = self.feet.to(device), self.ankle_height.to(device)
        self.arm_dofs, self.arm_rest = self.arm_dofs.to(device), self.arm_rest.to(device)
        self._stack = None
        return self

    @property
    def stack(self) -> SubjectStack:
        """This subject alone as a stack (it broadcasts over any number of states of this body)."""
        if self._stack is None:
            self._stack = SubjectStack([self])
        return self._stack


class SubjectStack:
    """B subjects' models stacked for the batched step: forward kinematics (:class:`SkeletonStack`), blobs and
    goals with a leading B on their per-subject geometry. A stack of one subject serves any number of states."""

    def __init__(self, subjects: Sequence[Subject]) -> None:
        first = subjects[0]
        self.subjects = tuple(subjects)
        self.skeleton = SkeletonStack([s.skeleton for s in subjects])
        self.blobs = BlobModel.stack([s.blobs for s in subjects])
        self.goals = GoalModel.stack([s.goals for s in subjects], self.blobs)
        self.ccd = first.ccd  # the solve's chain is given as frames; axes and limits are the bodies' shared ones
        self.ccd_goal_index, self.spine_dofs, self.feet = first.ccd_goal_index, first.spine_dofs, first.feet
        self.output_joint = first.output_joint
        self.attached = first.goals.attached.sum(0).clamp(min=1)  # (G,) blobs informing each joint
        self.ankle_height = torch.stack([s.ankle_height for s in subjects])  # (B, 2)
        self.dof_rz = first.skeleton.dof_names.index("root_rz")

    def clamp(self, angles: torch.Tensor) -> torch.Tensor:
        return self.skeleton.skeleton.clamp(angles)

    def gaussians(self, fk: FKResult) -> tuple[torch.Tensor, torch.Tensor]:
        return self.blobs.gaussians(fk.bone_frames)


@dataclass(frozen=True)
class VoxelBatch:
    """B frames' voxels padded to one size (N the most of any; C the most cameras of any).

    Attributes:
        points: (B, N, 3), NaN where padded. sizes, weights: (B, N), 0 where padded. colours: (B, N, C, 3), NaN
        where unseen or padded. cameras_valid: (B, C). camera_centres: (B, C, 3) (0 where unknown or padded).
        ghosts: (B,) bool host list, whether each frame's rig lets the ghost test run (centres known, at most
        ``ghost_max_cameras`` cameras); lower, upper: (B, 3) the observed volume's corners (+-inf: unbounded).
    """

    points: torch.Tensor
    sizes: torch.Tensor
    weights: torch.Tensor
    colours: torch.Tensor
    cameras_valid: torch.Tensor
    camera_centres: torch.Tensor
    ghosts: tuple[bool, ...]
    lower: torch.Tensor
    upper: torch.Tensor

    @classmethod
    def of(cls, observations: Sequence[VoxelObservation], ghost_max_cameras: int) -> VoxelBatch:
        """Pad ``observations`` (one frame each) into a batch."""
        ref = observations[0].points
        C = max(o.colours.shape[1] for o in observations)
        points = pad_rows([o.points for o in observations], math.nan)
        sizes = pad_rows([o.sizes.to(ref) for o in observations], 0.0)
        weights = pad_rows([o.weights for o in observations], 0.0)
        colours = pad_rows([o.colours if o.colours.shape[1] == C else
                            F.pad(o.colours, (0, 0, 0, C - o.colours.shape[1]), value=math.nan) for o in observations],
                           math.nan)  # cameras, then voxels
        valid = pad_rows([o.cameras_valid.to(ref.device) for o in observations], False)
        centres = pad_rows([ref.new_zeros(o.colours.shape[1], 3) if o.camera_centres is None else
                            o.camera_centres.to(ref) for o in observations], 0.0)
        box = [((-math.inf,) * 3, (math.inf,) * 3) if o.volume_m is None else o.volume_m for o in observations]
        lower, upper = host_tensor([b[0] for b in box], ref), host_tensor([b[1] for b in box], ref)
        ghosts = tuple(o.camera_centres is not None and o.camera_centres.shape[0] <= ghost_max_cameras
                       for o in observations)
        return cls(points, sizes, weights, colours, valid, centres, ghosts, lower, upper)

    def repeat(self, n: int) -> VoxelBatch:
        """One frame's batch as ``n`` copies of it (the hypotheses of that frame)."""
        return VoxelBatch(*(v.expand(n, *v.shape[1:]).contiguous() if isinstance(v, torch.Tensor) else v * n
                            for v in (self.points, self.sizes, self.weights, self.colours, self.cameras_valid,
                                      self.camera_centres, self.ghosts, self.lower, self.upper)))

    def outside(self, mean: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
        """(B, K) each blob's share out of its frame's volume (:func:`~torchtrack.tracking.voxels.share_outside`)."""
        return share_outside(mean, cov, self.lower.to(mean)[:, None], self.upper.to(mean)[:, None])


@dataclass(frozen=True)
class StepState:
    """What a step starts from, per frame of the batch.

    Attributes:
        angles, previous: (B, D) the last good pose and the one before (the prediction's velocity).
        velocity: (B,) the prediction's factor (0: the last pose).
        colour_mean, colour_cov, colour_known: (B, K, 3), (B, K, 3, 3), (B, K) the colour model carried.
        covers: (B, K) bool, the blobs that may explain a ghost's ray (those the last accepted frame filled).
        feet_seen: (B, 2, 2, 3) each foot's ankle and toe where last observed; feet_still (B, 2, 2) bool whether
            held while unobserved (False: not held). floor_z: (B,) the floor's height (for ``floor_contact``).
    """

    angles: torch.Tensor
    previous: torch.Tensor
    velocity: torch.Tensor
    colour_mean: torch.Tensor
    colour_cov: torch.Tensor
    colour_known: torch.Tensor
    covers: torch.Tensor
    feet_seen: torch.Tensor
    feet_still: torch.Tensor
    floor_z: torch.Tensor


@dataclass(frozen=True)
class Stepped:
    """The step's results, (B, ...) each (see :class:`~torchtrack.tracking.markerless.FrameResult`)."""

    angles: torch.Tensor
    output_points: torch.Tensor
    confidence: torch.Tensor
    residual_m: torch.Tensor
    explained: torch.Tensor
    blobs: Blobs
    bone_frames: torch.Tensor
    feet: torch.Tensor
    feet_observed: torch.Tensor
    prediction: torch.Tensor  #: (B, D) the predicted states the step started from
    prediction_bones: torch.Tensor  #: (B, nb, 4, 4) their bone frames


def host_tensor(values: Sequence, like: torch.Tensor, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``values`` (host numbers) as a tensor on ``like``'s device (in its dtype unless ``dtype``), copied to a GPU from
    pinned memory without waiting for the device (a copy from pageable memory synchronises the host)."""
    dtype = like.dtype if dtype is None else dtype
    if like.device.type != "cuda":
        return torch.tensor(values, dtype=dtype, device=like.device)
    return torch.tensor(values, dtype=dtype, pin_memory=True).to(like.device, non_blocking=True)


def pad_rows(rows: Sequence[torch.Tensor], value: float | bool) -> torch.Tensor:
    """``rows`` (n_b, ...) as one (B, max n_b, ...) tensor, padded with ``value``: all rows copied in one operation
    (``pad_sequence`` copies them one by one, which a GPU pays a kernel launch each for), in their promoted dtype
    (as ``torch.cat``) on the first row's device; a batch of one is a view of its row."""
    dtype = functools.reduce(torch.promote_types, [r.dtype for r in rows])
    rows = [r.to(device=rows[0].device, dtype=dtype) for r in rows]  # no copy where they are already
    lengths = [int(r.shape[0]) for r in rows]
    N, first = max(lengths), rows[0]
    if len(rows) == 1:
        return first[None]
    if min(lengths) == N:
        return torch.stack(list(rows))
    # each row's elements go to rows b * N .. b * N + n_b - 1 of the flattened batch
    starts = np.arange(len(rows)) * N - np.cumsum([0] + lengths[:-1])
    index = host_tensor(np.arange(sum(lengths)) + np.repeat(starts, lengths), first, torch.int64)
    out = first.new_full((len(rows) * N, *first.shape[1:]), value)
    return out.index_copy_(0, index, torch.cat(list(rows))).view(len(rows), N, *first.shape[1:])


def prior_state(angles: torch.Tensor, num_blobs: int, colour_std: float = 0.2) -> dict[str, torch.Tensor]:
    """The colour and feet fields of a :class:`StepState` for B states with nothing learnt (hypotheses)."""
    B, dev, dt = angles.shape[0], angles.device, angles.dtype
    return dict(colour_mean=angles.new_zeros(B, num_blobs, 3),
                colour_cov=(colour_std ** 2) * torch.eye(3, dtype=dt, device=dev).expand(B, num_blobs, 3, 3),
                colour_known=torch.zeros(B, num_blobs, dtype=torch.bool, device=dev),
                covers=torch.ones(B, num_blobs, dtype=torch.bool, device=dev),
                feet_seen=angles.new_zeros(B, 2, 2, 3), feet_still=torch.zeros(B, 2, 2, dtype=torch.bool, device=dev))


def goal_confidence(sub: SubjectStack, goal_w: torch.Tensor) -> torch.Tensor:
    """(B, G) goal weights -> each joint goal's confidence in [0, 1]: its weight over its blobs' count."""
    return (goal_w / sub.attached.to(goal_w)).clamp(0, 1)


def unwrap(angle: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """``angle`` moved by whole turns to within half a turn of ``reference``."""
    return angle + 2 * math.pi * torch.round((reference - angle) / (2 * math.pi))


def track_step(sub: SubjectStack, obs: VoxelBatch, state: StepState, config: StepConfig, learn_colour: bool,
               max_rot: float, predicted: bool = True, hold: bool = True) -> Stepped:
    """One frame of B sequences (or hypotheses) from their predicted poses (see the module docstring).

    Args:
        sub: the B frames' subjects (a stack of one serves B states of one body). obs: their voxels.
        state: where each starts from. learn_colour: the colour models learn from this frame.
        max_rot: bound on the root's rotation per pass (rad).
        predicted: trust the prediction, to explain ghost voxels away against it and to silence the blobs it puts
            out of the volume (off where it is only a guess: the hypotheses of a start or re-acquisition, which
            must be scored on the same goals). hold: hold unseen planted feet where they were last seen.
    """
    cfg = config
    a = sub.clamp(state.angles + state.velocity[:, None] * (state.angles - state.previous))
    fk = predicted_fk = sub.skeleton.forward(a)
    mean, cov = sub.gaussians(fk)  # (B, K, 3), (B, K, 3, 3)
    B, K = mean.shape[:2]
    prior = Blobs(mean, cov, state.colour_mean.to(mean), state.colour_cov.to(mean), state.colour_known,
                  mean.new_ones(B, K), torch.ones(B, K, dtype=torch.bool, device=mean.device))
    weights = obs.weights
    ghosts = [b for b, g in enumerate(obs.ghosts) if g] if predicted and cfg.ghost_weight < 1.0 else []
    if ghosts:
        i = host_tensor(ghosts, mean, torch.int64)
        seen = torch.isfinite(obs.colours[i]).all(-1) & obs.cameras_valid[i][:, None]
        ghost = ghost_voxels(obs.points[i], seen, obs.camera_centres[i], mean[i], cov[i], cfg.ghost_inside_scale,
                             cfg.ghost_cover_scale, state.covers[i], self_scale=cfg.ghost_self_scale)
        weights = weights.clone()
        weights[i] = torch.where(ghost, weights[i] * cfg.ghost_weight, weights[i])
    blobs, assign = fit_blobs(obs.points, weights, obs.sizes, obs.colours, prior, cfg.em, learn_colour=learn_colour)
    # a blob the volume's boundary cuts shows only its inside part: no goals from it
    seen_blobs = blobs.active & (obs.outside(mean, cov) <= MAX_OUTSIDE) if predicted else blobs.active
    weight = seen_blobs.to(a.dtype) * blobs.fill.clamp(0, 1)  # (B, K)
    goals = goal_w = None
    s = a
    for r in range(cfg.refinements):
        if r:  # the first pass starts from the prediction, whose kinematics the prior came from
            fk = sub.skeleton.forward(s)
        goals, goal_w = sub.goals.joint_goals(fk.bone_frames, blobs.mean, blobs.cov, weight)
        ik_goals, ik_w = goals, goal_w  # the residual and confidences below are the observation's
        if hold and cfg.hold_lost_feet > 0:  # unobserved feet that were still stay where last seen
            held = (goal_confidence(sub, goal_w)[:, sub.feet] < cfg.hold_min_confidence) & state.feet_still
            ik_goals, ik_w = ik_goals.clone(), ik_w.clone()
            ik_goals[:, sub.feet] = torch.where(held[..., None], state.feet_seen.to(goals), goals[:, sub.feet])
            ik_w[:, sub.feet] = torch.where(held, torch.full_like(ik_w[:, sub.feet], cfg.hold_lost_feet),
                                            ik_w[:, sub.feet])
        if cfg.floor_contact:  # where the floor is known (it is from the start on)
            floor = state.floor_z.to(goals)
            on = torch.isfinite(floor)
            g, w = floor_contact(ik_goals, ik_w, fk.joints, floor.nan_to_num(0.0), sub.feet,
                                 sub.ankle_height.to(goals).expand(B, -1))
            ik_goals, ik_w = torch.where(on[:, None, None], g, ik_goals), torch.where(on[:, None], w, ik_w)
        trunk = fk.joints
        if cfg.rigid_trunk:  # the root fits a straight trunk, CCD bends the spine from there
            s = s.index_fill(1, sub.spine_dofs, 0.0)
            trunk = sub.skeleton.forward(s).joints
        s = sub.goals.fit_root(s, trunk, ik_goals, ik_w, max_rotation=max_rot)
        s[:, sub.dof_rz] = unwrap(s[:, sub.dof_rz], a[:, sub.dof_rz])
        idx = sub.ccd_goal_index
        s = sub.ccd(s, ik_goals[:, idx], ik_w[:, idx], frames=sub.skeleton.forward_frames(s))
    fk = sub.skeleton.forward(s)
    residual = ((fk.joints - goals).norm(dim=-1) * goal_w).sum(-1) / goal_w.sum(-1).clamp(min=1e-12)  # (B,)
    # of all the voxels' weight, ghosts included: the divergence test must not grow blind with the ghost test
    explained = (obs.weights * (assign >= 0)).sum(-1) / obs.weights.sum(-1).clamp(min=1e-30)  # (B,)
    conf_joint = goal_confidence(sub, goal_w)  # (B, G)
    oj = sub.output_joint
    conf = torch.where(oj >= 0, conf_joint[:, oj.clamp(min=0)], conf_joint.mean(-1, keepdim=True))
    observed = conf_joint[:, sub.feet] >= cfg.hold_min_confidence
    return Stepped(s, fk.output_points, conf, residual, explained, blobs, fk.bone_frames, fk.joints[:, sub.feet],
                   observed, a, predicted_fk.bone_frames)


@dataclass(frozen=True)
class FrameResult:
    """One tracked frame.

    Attributes:
        angles: (D,) state vector. output_points: (22, 3) the skeleton's output points (``output_names``).
        confidence: (22,) 0..1 per output point. valid: whether the frame was tracked.
        residual_m: mean goal-to-joint distance after IK. explained: fraction of voxel weight in blobs. Both
            NaN where the images, not the voxels, placed the body (``TrackerConfig.image_hold_s``).
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

def moved_feet(position: torch.Tensor, observed: torch.Tensor, seen: torch.Tensor, still: torch.Tensor,
               max_step_m: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The held feet after an accepted frame (the tracker's ``_update_feet``), for one tracker or many at once (a
    leading batch): the solved ankles and toes ``position (..., 2, 2, 3)``, which of them the observation
    gave goals ``observed (..., 2, 2)``, and where each was last seen ``seen (..., 2, 2, 3)`` and whether still
    there ``still (..., 2, 2)`` -> the new ``seen`` and ``still``."""
    step = (position - seen).norm(dim=-1)  # m since it was last seen, however long ago
    return torch.where(observed[..., None], position, seen), torch.where(observed, step < max_step_m, still)
