"""The subject's bone lengths fitted at the start and by the body refit (:class:`~torchtrack.tracking.markerless.
MarkerlessTracker`'s part): the bone groups' lengths and the neck's height, by least squares on EM's blobs or by the
union of the body's ellipsoids fitted to the voxels (:mod:`torchtrack.blobs.shape`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from torchtrack.blobs.em import Blobs, fit_blobs, prior_blobs
from torchtrack.blobs.model import BlobModel
from torchtrack.blobs.shape import ShapeFrame, ShapeModel, fit_shape, fit_shape_frames
from torchtrack.checks import InputError, check_shape
from torchtrack.skeleton.model import Skeleton
from torchtrack.tracking.voxels import ViewSilhouettes, VoxelObservation
from torchtrack.tracking.step import FrameResult

#: Bones whose lengths are fitted together at initialisation (left and right tied).
#: Each limb's two long bones share one scale and the pelvis, hands and feet another (too small to measure
#: apart); torso and head are fitted separately, and the neck's height on the torso (NECK_JOINT). Real subjects'
#: proportions differ from the template's, which one scale cannot follow (docs/results.md, "Tracker settings").
BONE_GROUPS: tuple[tuple[str, ...], ...] = (
    ("pelvis", "l_hand", "r_hand", "l_foot", "r_foot"), ("torso",), ("head",),
    ("l_upperarm", "r_upperarm", "l_forearm", "r_forearm"), ("l_thigh", "r_thigh", "l_shank", "r_shank"))
#: The neck's height on the torso is fitted on top of the torso's scale (which moves the neck and the shoulders
#: together): subjects differ in how far the neck base sits above the shoulder joints. Finite-difference step (m).
NECK_JOINT, NECK_STEP_M = "neck_flex", 0.1
#: The bone fit's ridge on each group's change relative to the body the fit started from (the template scaled to
#: the voxels' height; for the torso its length, which is the neck's height on it), and on the neck's shift in
#: NECK_STEP_M towards each round's body (with the torso's length held, that shift sets the shoulders' height).
#: Towards the start because rounds towards their own last body drift along what the voxels hardly tell apart, the
#: torso's length against the head's (docs/results.md, "Tracker settings"; the shoulders held as well: "Tried and
#: dropped").
BONE_FIT_RIDGE = 0.02
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
#: The girths the start tries (every blob's two cross semi-axes times each: :class:`~torchtrack.tracking.step.
#: Subject`), the one whose masks best overlap the cameras' foreground kept. Subjects are stouter or slimmer than the
#: template, and on a few views' hull a body too slim sinks into the phantom volume around it. 0.8-1.3: the builds
#: the tracker models (the stress table draws 0.85-1.3); where the pose is off, a stouter body covers the misplaced
#: limb too and the fit reads stout, and up to 1.4 a stout subject's start was once decided turned round
#: (docs/results.md, "The subject's girth").
GIRTHS = tuple(round(0.8 + 0.05 * i, 2) for i in range(11))
#: The bone fit's EM sees the voxels split to at most this size (:meth:`VoxelObservation.split`): the hull's
#: coarse interior cubes (6-12 cm) each went whole to one blob, and at the hips they gave the thighs' tops to the
#: pelvis and the legs came out short (docs/results.md, "Tracker settings"). The Bayesian grid's voxels (3 cm) are
#: not split.
BONE_FIT_VOXEL_M = 0.03


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


class BoneFitMixin:
    """The bone fit's methods of :class:`~torchtrack.tracking.markerless.MarkerlessTracker`."""

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
                obs = self._without_floor_band(obs).split(BONE_FIT_VOXEL_M)
                p = self._bone_fit_problem(obs, a.to(self.subject.blobs.semi_axes), start_body, SHAPE_FIT_RIDGE)
                frames.append(ShapeFrame(p.model, obs.points, obs.sizes, p.weights, obs.volume_m))
        finally:
            self.colour = colour
        # the ridge depends only on the current and the start body, the same for every frame: the last frame's
        shared, _, _ = fit_shape_frames(frames, p.ridge_w[:-3], p.target[:-3],
                                        [x0[:-3] for x0 in self._shape_starts(p.target.device)], local=3,
                                        progress=progress)
        return self._apply_bone_fit(torch.cat([shared, shared.new_zeros(3)]), angles.device)

    def _fit_girth(self, obs: VoxelObservation, angles: torch.Tensor) -> float:
        """The subject's girth (:data:`GIRTHS`) at the pose ``angles (D,)``: the one whose blobs' masks (each view's
        exact ray cast, :func:`~torchtrack.tracking.clearance.body_masks`, pooled to the foreground's cells as the
        observation pools its foreground) best overlap the foreground cells of the readable cameras (intersection
        over union, pooled over them). On the voxels a stouter body always explains more of a few views' phantom
        volume, which the cameras' foreground does not hold. The current girth where ``obs`` keeps no foreground."""
        from torchtrack.occupancy.metrics import iou
        from torchtrack.tracking.clearance import PixelTiles, body_masks

        sil = obs.silhouettes
        if sil is None:
            return self.girth
        readable = obs.cameras_valid.to(sil.fg.device)[:, None, None]
        fg = sil.fg & readable  # (C, h, w)
        if not bool(fg.any()):
            return self.girth
        sub, tiles = self.subject, PixelTiles(sil.rig)
        overlap = []
        for g in GIRTHS:  # one ray cast a girth (0.2 s for 4 cameras at 320x240, a few % of a start)
            blobs = sub.blobs.widened(g / sub.girth)
            masks = body_masks(sil.rig, sub.skeleton, angles[None], blobs=blobs, tiles=tiles)[0]  # (C, H, W)
            cells = ViewSilhouettes.from_evidence(2.0 * masks.float() - 1.0, sil.rig, sil.cell_px).fg & readable
            overlap.append(iou(cells, fg))
        return GIRTHS[overlap.index(max(overlap))]

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
