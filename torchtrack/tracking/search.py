"""Start anywhere: the whole body's state searched for in one frame's voxels (ALGORITHMS.md §6).

A batch of hypotheses of the state (each a pose, a heading, a size and a place on the floor) is scored against
the observation in both directions (:func:`two_way_score`): the share of the voxel weight inside the body's blobs
and the share of the body's volume on occupied voxels; or, where the observation keeps each camera's foreground
(``observation.silhouettes``), the same two shares camera by camera in the images (:func:`image_terms`), where the
phantom volume of a few views' hull does not count against the true body and one camera's miss costs only that
camera's share (docs/results.md, "The start search"). Each limb of the best is swept over a grid of its main
joints, one limb after another, each candidate sized anew (the prior's poses are a few per limb: a walker's arm
swung between two of them is otherwise left to the annealing, which rarely gets there), and they are refined by an
annealed search (the hypotheses perturbed, re-scored and the best kept, layer after layer, with shrinking steps).
Where the images score them, half of those kept at every stage face away from the best, so that a body turned
round stays among them until the score tells it. The tracker's own EM/CCD then finishes the best few
(:meth:`MarkerlessTracker.initialize`). Every stage is one batched tensor computation over the hypotheses, on the
device of the voxels.

The hypotheses: the skeleton's poses from a structured prior (:func:`~torchtrack.tracking.poses.pose_prior`: arms
hanging, bent, forward, sideways, raised, each side on its own; legs standing, apart, stepping, squatting, a knee
raised, kicking; from 7 cameras also stooped over, ``stooped``) and, with ``real_poses``, from real captures
(:func:`~torchtrack.tracking.poses.real_pose_prior`: crouches, twists and reaches that no product of per-limb poses
gives), at every heading; placed with their lowest point on the floor (the voxels' lowest) and the centroid of their
blobs over the voxels' centroid, scaled so that their top meets the voxels' top (within ``scale_range``: the template
is the prior of the subject's size, whose proportions the tracker's bone fit then measures).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from torchtrack.blobs.em import quadric_distance2
from torchtrack.blobs.model import BlobModel, ellipsoid_covariance
from torchtrack.blobs.shape import unit_ball_samples
from torchtrack.checks import InputError
from torchtrack.skeleton.model import Skeleton
from torchtrack.tracking.ghosts import ghost_voxels
from torchtrack.tracking.poses import ARM_POSES, pose_prior, real_pose_prior
from torchtrack.tracking.voxels import ViewSilhouettes, VoxelObservation

__all__ = ["NearResult", "SearchConfig", "SearchResult", "score_states", "search_near_in_images", "search_pose",
           "sweep_limbs", "two_way_score"]

#: The body's DOFs the annealed search perturbs, with the step (rad) of its first layer.
STEP_RAD = 0.3
#: A voxel counts as inside a blob within this factor of its ellipsoid (voxels stick out of the body's surface by
#: half a voxel, and the blobs are the template's, not the subject's, shape).
INSIDE_GROW = 1.2
#: Occupancy of the body's volume is looked up on a grid of this cell, dilated by one cell (m).
CELL_M = 0.03
#: The limb sweep's grids (rad): per arm, shoulder flexion x abduction x elbow flexion; per leg, hip flexion x
#: abduction x knee flexion. Each limb of each kept hypothesis is set to every point, the rest of the body kept.
ARM_GRID = ((-0.6, 0.0, 0.6, 1.2, 1.8, 2.6), (0.1, 0.5, 1.0, 1.6), (0.1, 0.8, 1.6))
LEG_GRID = ((-0.4, 0.0, 0.5, 1.0, 1.5), (0.0, 0.3), (0.1, 0.9, 1.8))
#: Where the images compare finished bodies (:data:`IMAGE_COMPARE_MIN_CAMERAS`), the prior's poses also stooped
#: over (spine and neck flexion added, rad) and the arm sweep's elbow also folded to a hand at the chest: an upright
#: pose meets a crouched body's voxels only shrunk to their top, and the annealing's one-part steps do not bend the
#: trunk from there (the bend lowers the top that sized the pose). On fewer views the hull's phantom volume takes
#: the stooped poses in (docs/results.md, "The stooped trunk, tried everywhere").
STOOP = {"spine_flex": 0.5, "neck_flex": 0.9}
STOOPED_ELBOW = 2.3


@dataclass(frozen=True)
class SearchConfig:
    """How hard the start search looks.

    Attributes:
        headings: headings tried for every prior pose (evenly all round).
        keep: hypotheses carried from one stage to the next (and into the annealed search).
        particles: hypotheses per layer of the annealed search.
        layers: layers of the annealed search; the steps shrink by ``shrink`` per layer.
        shrink: step factor per layer.
        max_voxels: voxels the voxel-to-body term is evaluated on (a weighted subsample beyond).
        samples: points per blob of the body-to-voxel term.
        scale_range: the subject's size relative to the skeleton searched with (the template: 0.8-1.2, a
            subject 1.40-2.10 m tall; a known body, re-acquired: 1).
        sweep: before the annealing, each limb of each kept hypothesis swept over a grid of its main joints
            (:data:`ARM_GRID`, :data:`LEG_GRID`), one limb after another, the best kept, each candidate sized as the
            first stages size a pose (its top at the voxels' top). Only where the images score the body
            (``observation.silhouettes``), unless ``sweep_voxels``: on a few views' hull the sweep fits limbs into
            phantom volume (docs/results.md, "The limb sweep").
        stooped: the prior's poses also stooped over (:data:`STOOP`) and the arm sweep's elbow also at
            :data:`STOOPED_ELBOW`, on rigs of :data:`IMAGE_COMPARE_MIN_CAMERAS` cameras and more where the images
            score the body; for starts and re-acquisitions alike.
        real_poses: add the real captures' poses (:func:`~torchtrack.tracking.poses.real_pose_prior`) to the
            structured prior (``TrackerConfig.start_real_poses``).
        prior_exclude: leave out the real poses whose capture's name contains one of these (an evaluation on a
            capture the prior was built from leaves its subject out).
    """

    headings: int = 24
    keep: int = 16
    particles: int = 192
    layers: int = 14
    shrink: float = 0.7
    max_voxels: int = 1500
    samples: int = 24
    scale_range: tuple[float, float] = (0.8, 1.2)
    sweep: bool = True
    sweep_voxels: bool = False
    stooped: bool = True
    real_poses: bool = False
    prior_exclude: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if min(self.headings, self.keep, self.particles, self.max_voxels, self.samples) < 1 or self.layers < 0:
            raise InputError(f"SearchConfig: counts must be >= 1 (layers >= 0), got {self}")
        if not 0 < self.shrink <= 1 or not 0 < self.scale_range[0] <= self.scale_range[1]:
            raise InputError(f"SearchConfig: shrink in (0, 1] and 0 < scale_range[0] <= [1], got {self}")


@dataclass(frozen=True)
class SearchResult:
    """The best hypotheses, best first (``n`` of them).

    Attributes:
        angles: (n, D) state vectors of the skeleton scaled by ``scale`` (root placed in the world).
        scale: (n,) size relative to the skeleton searched with.
        score: (n,) :func:`two_way_score`; explained, filled: (n,) its two terms.
        outside: (n,) share of the body's volume out of the observed volume.
        hypotheses: how many were scored in all.
    """

    angles: torch.Tensor
    scale: torch.Tensor
    score: torch.Tensor
    explained: torch.Tensor
    filled: torch.Tensor
    outside: torch.Tensor
    hypotheses: int


class _Voxels:
    """The frame's voxels as the score reads them: a weighted subsample, and a dense occupancy grid."""

    def __init__(self, obs: VoxelObservation, max_voxels: int, generator: torch.Generator | None,
                 own_ghosts: bool = False) -> None:
        pts, w = obs.points.float(), obs.weights.float()
        own_ghosts = own_ghosts and obs.camera_centres is not None
        # each body's own ghosts (two_way_score) need where the cameras are and which of them see each voxel
        seen = torch.isfinite(obs.colours).all(-1) & obs.cameras_valid.to(pts.device)[None] if own_ghosts else None
        if pts.shape[0] > max_voxels:  # a weighted subsample without replacement: the same share per weight
            at = w if generator is None else w.to(generator.device)  # drawn where the generator lives
            pick = torch.multinomial(at, max_voxels, replacement=False, generator=generator).to(pts.device)
            pts, w, seen = pts[pick], w[pick], None if seen is None else seen[pick]
        self.points, self.weights = pts, w / w.sum()
        self.ghost_views = (seen, obs.camera_centres.to(pts)) if own_ghosts else None  # (N, C), (C, 3)
        fine = obs.split(CELL_M)
        p = fine.points.float()
        self.lower = p.amin(0) - 3 * CELL_M
        shape = ((p.amax(0) + 3 * CELL_M - self.lower) / CELL_M).ceil().long() + 1
        self.shape = shape
        idx = ((p - self.lower) / CELL_M).floor().long()
        grid = torch.zeros(tuple(shape.tolist()), dtype=torch.float32, device=p.device)
        grid[idx[:, 0], idx[:, 1], idx[:, 2]] = 1.0
        self.grid = F.max_pool3d(grid[None, None], 3, stride=1, padding=1)[0, 0] > 0  # dilated by one cell
        self.volume = None if obs.volume_m is None else tuple(torch.tensor(v, dtype=torch.float32,
                                                                           device=p.device) for v in obs.volume_m)
        self.centroid = (obs.weights.float()[:, None] * obs.points.float()).sum(0) / obs.weights.float().sum()
        self.floor, self.top = obs.height_span()
        views = None if obs.silhouettes is None else _Views(obs.silhouettes, obs.cameras_valid)
        self.views = views if views is not None and bool(views.used.any()) else None  # no foreground: the voxels

    def occupied(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) points -> (occupied, observed) bool: on an occupied cell; inside the observed volume."""
        idx = ((q - self.lower) / CELL_M).floor().long()
        inside = ((idx >= 0) & (idx < self.shape)).all(-1)
        i = idx.clamp(min=0)
        i = torch.minimum(i, self.shape - 1)
        occ = self.grid[i[..., 0], i[..., 1], i[..., 2]] & inside
        observed = q[..., 2] >= self.floor
        if self.volume is not None:
            lo, hi = self.volume
            observed = observed & (q[..., :2] >= lo[:2]).all(-1) & (q <= hi).all(-1)
        return occ, observed


class _Views:
    """Each readable camera's foreground cells as the image term reads them: their centres in pixels (padded per
    camera) and the cells as a lookup."""

    def __init__(self, sil: ViewSilhouettes, cameras_valid: torch.Tensor) -> None:
        self.rig, self.cell = sil.rig, float(sil.cell_px)
        self.fg = sil.fg & cameras_valid.to(sil.fg.device)[:, None, None]  # (C, h, w)
        C, h, w = self.fg.shape
        counts = self.fg.flatten(1).sum(1)  # (C,)
        n = max(int(counts.max()), 1)
        self.cells = torch.zeros(C, n, 2, device=self.fg.device)
        self.cell_ok = torch.zeros(C, n, dtype=torch.bool, device=self.fg.device)
        cam, iv, iu = self.fg.nonzero(as_tuple=True)  # row-major: grouped by camera
        rank = torch.arange(cam.shape[0], device=cam.device) - (torch.cumsum(counts, 0) - counts)[cam]
        self.cells[cam, rank] = torch.stack([iu, iv], -1).float() * self.cell + 0.5 * (self.cell - 1)
        self.cell_ok[cam, rank] = True
        self.counts = counts.float()
        self.used = counts > 0  # cameras whose foreground the term compares

    def lookup(self, uv: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """(C, ..., 2) pixels, (C, ...) valid -> (C, ...) bool: on a foreground cell."""
        C, h, w = self.fg.shape
        iu = torch.floor((uv[..., 0] + 0.5) / self.cell).long().clamp(0, w - 1)
        iv = torch.floor((uv[..., 1] + 0.5) / self.cell).long().clamp(0, h - 1)
        cam = torch.arange(C, device=uv.device).reshape(C, *([1] * (uv.dim() - 2)))
        return self.fg[cam.expand_as(iu), iv, iu] & valid


#: :func:`score_states` compares finished bodies in the images from this many cameras, on the voxels below it. On
#: a few views the images find the body's basin more often than the voxels, whose hull holds phantom volume (the
#: search), but they score close variants within it alike: a forearm held before the trunk, which 4 views all
#: hide, against the one hanging; a starfish start turned round, 0.005 under its twin in 4 cameras' images, inside
#: the start race's margin, and 0.014 under it on the voxels (docs/results.md, "The start search"). On the voxels each
#: body's own ghosts are left out of the share it must explain (:func:`two_way_score`): the forearm before the trunk
#: sits in phantom volume the hanging one leaves as ghosts of the body.
IMAGE_COMPARE_MIN_CAMERAS = 7


def _images_compare(obs: VoxelObservation) -> bool:
    """Whether the rig of ``obs`` has :data:`IMAGE_COMPARE_MIN_CAMERAS` cameras (the score's and the stooped
    prior's gate; the rig's cameras, not the readable ones)."""
    return obs.cameras_valid.numel() >= IMAGE_COMPARE_MIN_CAMERAS


#: Finite-difference step (m) of the projection's Jacobian at each blob's centre (the image term's ellipses).
JACOBIAN_STEP_M = 1e-3


#: The image term's ellipse test holds (cameras, hypotheses, blobs, cells) elements per step: as many hypotheses
#: per step as keep it within this many (16 MB per float32 temporary), at least one.
IMAGE_TERM_ELEMENTS = 1 << 22


def _covered(cu: torch.Tensor, cv: torch.Tensor, m: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor,
             front: torch.Tensor) -> torch.Tensor:
    """(C, h, N) bool: each cell (``cu, cv (C, 1, 1, N)``) inside the ellipse of some blob (centres ``m (C, h, K,
    2)``, inverse covariance ``[[a, b], [b, c]]``, each (C, h, K, 1)) in front of the lens-model fold."""
    du, dv = cu - m[..., 0, None], cv - m[..., 1, None]  # (C, h, K, N)
    quad = a * du * du + 2.0 * b * du * dv + c * dv * dv
    return ((quad <= 1.0) & front[..., None]).any(2)


def _on_foreground(q: torch.Tensor, views: _Views) -> tuple[torch.Tensor, torch.Tensor]:
    """The body's sample points ``q (h, K, S, 3)`` in each camera -> (C, h, K) each blob's share of its points on
    the camera's foreground cells, and its share in the camera's image."""
    h, K = q.shape[:2]
    uvq, okq = views.rig.project(q.reshape(h, -1, 3))  # (C, h, KS, 2)
    C = uvq.shape[0]
    on = views.lookup(uvq, okq).float().reshape(C, h, K, -1).mean(-1)
    return on, okq.float().reshape(C, h, K, -1).mean(-1)


def image_terms(centres: torch.Tensor, R: torch.Tensor, semi_axes: torch.Tensor, q: torch.Tensor, vol: torch.Tensor,
                views: _Views) -> tuple[torch.Tensor, torch.Tensor]:
    """The two terms of the score in the images, camera by camera (a camera's miss or the hull's phantom volume
    then costs only that camera's share).

    explained: the share of each camera's foreground cells inside the projection of some blob grown by
    INSIDE_GROW (each ellipsoid projected as the ellipse of its linearised projection at the centre); filled: the
    share of the body's sample points ``q (h, K, S, 3)`` (by blob volume ``vol (h, K)``) on foreground cells,
    over the points the cameras see. Over the cameras with foreground: explained averaged, filled pooled (each
    camera by how much of the body it sees). Returns two (h,).
    Hand-written: neither kornia nor OpenCV projects an ellipsoid through a lens model."""
    rig = views.rig
    h, K = centres.shape[:2]
    eye = torch.eye(3, dtype=centres.dtype, device=centres.device)
    probe = torch.cat([centres[:, :, None], centres[:, :, None] + JACOBIAN_STEP_M * eye], 2)  # (h, K, 4, 3)
    uv, ok = rig.project(probe.reshape(-1, 4, 3))  # (C, hK, 4, 2)
    C = uv.shape[0]
    m = uv[:, :, 0].reshape(C, h, K, 2)
    J = ((uv[:, :, 1:] - uv[:, :, :1]) / JACOBIAN_STEP_M).transpose(-1, -2).reshape(C, h, K, 2, 3)
    front = rig.in_lens_model(centres.reshape(-1, 3)).reshape(C, h, K)  # else the ellipse is meaningless
    sig = R @ torch.diag_embed((INSIDE_GROW * semi_axes) ** 2) @ R.transpose(-1, -2)  # (h, K, 3, 3)
    S2 = J @ sig[None] @ J.transpose(-1, -2)  # (C, h, K, 2, 2)
    Sinv = torch.linalg.inv(S2 + 1e-6 * torch.eye(2, dtype=S2.dtype, device=S2.device))
    # each cell against each blob's ellipse, (d^T Sinv d <= 1 expanded in d's two coordinates), a few hypotheses at
    # a time: (C, hypotheses, K, N) per step, within IMAGE_TERM_ELEMENTS (at least one hypothesis)
    a, b, c = (Sinv[..., 0, 0, None], Sinv[..., 0, 1, None], Sinv[..., 1, 1, None])  # (C, h, K, 1)
    cu, cv = views.cells[:, None, None, :, 0], views.cells[:, None, None, :, 1]  # (C, 1, 1, N)
    N = views.cells.shape[1]
    step = max(1, IMAGE_TERM_ELEMENTS // max(1, C * K * N))
    covered = torch.cat([_covered(cu, cv, m[:, i:i + step], a[:, i:i + step], b[:, i:i + step],
                                  c[:, i:i + step], front[:, i:i + step]) for i in range(0, h, step)], 1)
    covered = covered & views.cell_ok[:, None]  # (C, h, N)
    explained_c = covered.float().sum(-1) / views.counts.clamp(min=1)[:, None]  # (C, h)
    on, seen = _on_foreground(q, views)  # (C, h, K)
    used = views.used.float()[:, None]
    n = used.sum().clamp(min=1.0)  # no camera with foreground: both terms 0
    # filled: pooled over the cameras by what each sees of the body (one that sees none of it has no say)
    filled = ((on * vol).sum(-1) * used).sum(0) / ((seen * vol).sum(-1) * used).sum(0).clamp(min=1e-12)
    return (explained_c * used).sum(0) / n, filled


def ellipsoid_distance2(points: torch.Tensor, centres: torch.Tensor, R: torch.Tensor, semi_axes: torch.Tensor
                        ) -> torch.Tensor:
    """(N, 3) points, ellipsoids (H, K) -> (N, H, K) ``|diag(1/a) R^T (p - c)|^2``, the squared normalised distance
    of every point from every ellipsoid's centre (<= 1 inside it): each ellipsoid's quadric ``A = R diag(1/a^2)
    R^T`` in :func:`~torchtrack.blobs.em.quadric_distance2`'s one matrix product (the plain form's (H, K, N, 3)
    offsets, each turned by its own rotation, cost ten times as much and were nine tenths of the search's time)."""
    N, (H, K) = points.shape[0], centres.shape[:2]
    A = (R / semi_axes[..., None, :].square()) @ R.transpose(-1, -2)  # (H, K, 3, 3)
    return quadric_distance2(points, centres.reshape(H * K, 3), A.reshape(H * K, 3, 3)).view(N, H, K)


def two_way_score(centres: torch.Tensor, R: torch.Tensor, semi_axes: torch.Tensor, vox: _Voxels,
                  samples: torch.Tensor, chunk: int = 64) -> tuple[torch.Tensor, ...]:
    """How well each hypothesis' blobs and the voxels explain each other.

    Args:
        centres (H, K, 3), R (H, K, 3, 3) (columns: the ellipsoids' axes), semi_axes (H, K, 3): the blobs as
            solid ellipsoids. vox: the frame's voxels. samples: (S, 3) points in the unit ball.

    Returns:
        score (H,): the harmonic mean of ``explained`` (the share of the voxel weight inside some blob grown by
        INSIDE_GROW; where ``vox`` knows the cameras' views, of the voxels that are not the body's own ghosts, those
        it explains in every view that sees them: a few views' phantom volume counts neither for a body nor against
        the one it is a ghost of) and ``filled`` (the share of the body's volume, over what the cameras observe, on
        occupied voxels), or of their counterparts in the images where ``vox`` has them (:func:`image_terms`);
        ``explained``, ``filled`` and ``outside`` (the share of the body's volume out of the observed volume),
        each (H,).
    """
    H, K, _ = centres.shape
    vol = semi_axes.prod(-1)  # (H, K) proportional to each blob's volume
    out = []
    for s in range(0, H, chunk):
        c, Rs, a = centres[s:s + chunk], R[s:s + chunk], semi_axes[s:s + chunk]
        q = c[:, :, None] + torch.einsum("hkij,hksj->hksi", Rs, a[:, :, None] * samples[None, None])  # (h,K,S,3)
        occ, seen = vox.occupied(q)
        v = vol[s:s + chunk]
        seen_v = (seen.float().mean(-1) * v).sum(-1)  # (h,)
        outside = 1.0 - seen_v / v.sum(-1)
        if vox.views is not None:  # the images' terms instead of the voxels' (see image_terms)
            explained, filled = image_terms(c, Rs, a, q, v, vox.views)
        else:
            # voxels -> body: the weight of the voxels inside some blob grown by INSIDE_GROW
            inside = (ellipsoid_distance2(vox.points, c, Rs, a) <= INSIDE_GROW ** 2).any(-1)  # (N, h)
            if vox.ghost_views is None:
                explained = vox.weights @ inside.float()  # (h,)
            else:  # of the voxels that are not the body's own ghosts
                real = ~_own_ghosts(vox, c, Rs, a).T  # (N, h)
                w = vox.weights[:, None] * real
                explained = (w * inside).sum(0) / w.sum(0).clamp(min=1e-12)
            # body -> voxels: each blob's sample points on occupied cells, over the observed ones
            filled = ((occ & seen).float().mean(-1) * v).sum(-1) / seen_v.clamp(min=1e-12)
        out.append(torch.stack([explained, filled, outside], -1))
    e, f, o = torch.cat(out).unbind(-1)
    return 2 * e * f / (e + f).clamp(min=1e-12), e, f, o


def _own_ghosts(vox: _Voxels, centres: torch.Tensor, R: torch.Tensor, semi_axes: torch.Tensor) -> torch.Tensor:
    """(h, N) the voxels each of h bodies (solid ellipsoids ``centres (h, K, 3)``, axes ``R``, ``semi_axes``) explains
    away as its own ghosts in every view that sees them (:func:`~torchtrack.tracking.ghosts.ghost_voxels`, its
    default scales)."""
    seen, cams = vox.ghost_views
    h, N = centres.shape[0], vox.points.shape[0]
    return ghost_voxels(vox.points.expand(h, N, 3), seen.expand(h, *seen.shape), cams.expand(h, *cams.shape),
                        centres, ellipsoid_covariance(R, semi_axes))


class _Hypotheses:
    """Poses at the origin (root translation and rotation zero), a heading, a scale and a place: the blobs of
    each in the world, and the state vector of the scaled skeleton."""

    def __init__(self, skel: Skeleton, blobs: BlobModel, vox: _Voxels) -> None:
        self.skel, self.blobs, self.vox = skel, blobs, vox
        names = list(skel.dof_names)
        self.root = [names.index(n) for n in ("root_tx", "root_ty", "root_tz", "root_rz", "root_ry", "root_rx")]

    def place(self, poses: torch.Tensor, heading: torch.Tensor, scale: torch.Tensor, shift: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(H, D) poses (root rotation ry/rx kept, the rest of the root ignored), (H,) headings and scales, (H, 2)
        shifts on the floor -> blob centres (H, K, 3), axes (H, K, 3, 3), semi-axes (H, K, 3) in the world and
        the (H, D) state vectors of the skeleton scaled by ``scale``."""
        a = poses.clone()
        a[:, self.root[:4]] = 0.0
        fk = self.skel.forward(a)
        c, R = self.blobs.ellipsoids(fk.bone_frames)  # (H, K, 3), (H, K, 3, 3) at the origin
        semi = self.blobs.semi_axes.to(c)[None].expand(c.shape[0], -1, -1)
        reach = (R * semi[:, :, None, :]).square().sum(-1).sqrt()  # (H, K, 3) half extent along x, y, z
        low = (c[..., 2] - reach[..., 2]).amin(1)  # (H,) lowest point of the body
        vol = semi.prod(-1)  # (H, K)
        mid = (vol[..., None] * c).sum(1) / vol.sum(1, keepdim=True)  # (H, 3) the blobs' centroid
        cz, sz = heading.cos(), heading.sin()
        Rz = torch.zeros(heading.shape[0], 3, 3, dtype=c.dtype, device=c.device)
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = cz, -sz, sz, cz, 1.0
        base = c - torch.stack([mid[:, 0], mid[:, 1], low], -1)[:, None]  # centroid over the origin, feet at 0
        s = scale[:, None, None]
        centres = torch.einsum("hij,hkj->hki", Rz, s * base)
        offset = torch.cat([self.vox.centroid[:2].to(c) + shift, c.new_full((1,), self.vox.floor).expand(
            shift.shape[0], 1)], -1)  # (H, 3)
        centres = centres + offset[:, None]
        axes = Rz[:, None] @ R
        root = torch.einsum("hij,hj->hi", Rz, scale[:, None] * (-torch.stack([mid[:, 0], mid[:, 1], low], -1)))
        root = root + offset
        state = poses.clone()
        state[:, self.root[0]], state[:, self.root[1]], state[:, self.root[2]] = root.unbind(-1)
        state[:, self.root[3]] = heading
        return centres, axes, s * semi, state

    def initial_scale(self, poses: torch.Tensor, scale_range: tuple[float, float]) -> torch.Tensor:
        """(H,) the scale at which each pose's top meets the voxels' top, within ``scale_range``."""
        a = poses.clone()
        a[:, self.root[:4]] = 0.0
        c, R = self.blobs.ellipsoids(self.skel.forward(a).bone_frames)
        semi = self.blobs.semi_axes.to(c)[None]
        zr = (R[..., 2, :] * semi).norm(dim=-1)  # (H, K) half extent along z
        height = (c[..., 2] + zr).amax(1) - (c[..., 2] - zr).amin(1)
        return ((self.vox.top - self.vox.floor) / height).clamp(*scale_range)


#: The parts of the body the annealed search changes one at a time (DOF name prefixes; "root_r": the tilt, with
#: the place).
GROUPS = (("root_ry", "root_rx"), ("spine_", "neck_"), ("l_shoulder", "l_elbow", "l_wrist"),
          ("r_shoulder", "r_elbow", "r_wrist"), ("l_hip", "l_knee", "l_ankle"), ("r_hip", "r_knee", "r_ankle"))


def _limb_grids(skel: Skeleton, stooped: bool = False) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per limb, its swept DOFs' indices ``(3,)`` and the grid's values ``(V, 3)`` (:data:`ARM_GRID`,
    :data:`LEG_GRID`; with ``stooped`` the arms' elbows also at :data:`STOOPED_ELBOW`)."""
    names, dev = list(skel.dof_names), skel.lower.device
    arm = ARM_GRID[:2] + (ARM_GRID[2] + (STOOPED_ELBOW,),) if stooped else ARM_GRID
    out = []
    for side in "lr":
        for joints, grid in ((("shoulder_flex", "shoulder_abd", "elbow_flex"), arm),
                             (("hip_flex", "hip_abd", "knee_flex"), LEG_GRID)):
            idx = torch.tensor([names.index(f"{side}_{j}") for j in joints], device=dev)
            out.append((idx, torch.cartesian_prod(*(torch.tensor(g, device=dev) for g in grid)).float()))
    return out


def _limb_candidates(poses: torch.Tensor, idx: torch.Tensor, values: torch.Tensor, lo: torch.Tensor,
                     hi: torch.Tensor) -> torch.Tensor:
    """(H * V, D) each of the H states ``poses (H, D)`` with its DOFs ``idx`` set to every row of ``values (V, 3)``
    (one limb's grid, :func:`_limb_grids`), within the joint limits ``lo``, ``hi``; grouped by state."""
    H, V = poses.shape[0], values.shape[0]
    cand = poses.repeat_interleave(V, 0)
    cand[:, idx.to(cand.device)] = values.to(cand).repeat(H, 1)
    return torch.maximum(torch.minimum(cand, hi), lo)


def _dof_groups(skel: Skeleton) -> torch.Tensor:
    """(G, D) float masks of :data:`GROUPS`' DOFs."""
    out = torch.zeros(len(GROUPS), skel.num_dofs, device=skel.lower.device)
    for g, prefixes in enumerate(GROUPS):
        for d, name in enumerate(skel.dof_names):
            if name.startswith(prefixes):
                out[g, d] = 1.0
    return out


def score_states(obs: VoxelObservation, skel: Skeleton, blobs: BlobModel, angles: torch.Tensor,
                 samples: int = SearchConfig.samples, max_voxels: int = SearchConfig.max_voxels
                 ) -> tuple[torch.Tensor, ...]:
    """:func:`two_way_score` (score, explained, filled, outside; each (n,)) of the states ``angles (n, D)`` of
    ``skel`` (placed as they are) on ``obs``: to compare hypotheses that EM/IK has finished. The voxel subsample is
    the same for every call on ``obs``. In the images where ``obs`` keeps them, from
    :data:`IMAGE_COMPARE_MIN_CAMERAS` cameras; on fewer, on the voxels, each body's own ghosts left out where ``obs``
    has the cameras' centres."""
    return _score_finished(_compare_voxels(obs, max_voxels), skel, blobs, angles, samples)


def _compare_voxels(obs: VoxelObservation, max_voxels: int = SearchConfig.max_voxels) -> _Voxels:
    """The frame as :func:`score_states` compares finished bodies on it (the images from
    :data:`IMAGE_COMPARE_MIN_CAMERAS` cameras, else the voxels; the same subsample at every call)."""
    if obs.silhouettes is not None and not _images_compare(obs):
        obs = replace(obs, silhouettes=None)
    return _Voxels(obs, max_voxels, torch.Generator(device=obs.points.device).manual_seed(0),
                   own_ghosts=not _images_compare(obs))


def _score_finished(vox: _Voxels, skel: Skeleton, blobs: BlobModel, angles: torch.Tensor,
                    samples: int = SearchConfig.samples) -> tuple[torch.Tensor, ...]:
    """:func:`score_states` on a frame :func:`_compare_voxels` made once."""
    c, R = blobs.ellipsoids(skel.forward(angles.to(skel.lower)).bone_frames)
    semi = blobs.semi_axes.to(c)[None].expand(c.shape[0], -1, -1)
    pts = unit_ball_samples(samples, dtype=torch.float32, device=vox.points.device)
    return two_way_score(c.float(), R.float(), semi.float(), vox, pts)


def sweep_limbs(obs: VoxelObservation, skel: Skeleton, blobs: BlobModel, angles: torch.Tensor
                ) -> tuple[torch.Tensor, float, float]:
    """The limb sweep of the search (:data:`ARM_GRID`, :data:`LEG_GRID`; the folded elbow where the images compare
    finished bodies) on one finished state ``angles (D,)`` of ``skel``, placed and sized as it is: each limb in
    turn set to every point of its grid, the rest of the body kept, scored as finished bodies are compared
    (:func:`score_states`), the best kept where it beats the state so far. Returns the swept state, its score and
    the score of ``angles``."""
    lo, hi = skel.lower.to(angles), skel.upper.to(angles)
    vox = _compare_voxels(obs)  # built once for every limb's candidates
    start = float(_score_finished(vox, skel, blobs, angles[None])[0][0])
    best, pose = start, angles
    for idx, values in _limb_grids(skel, _images_compare(obs)):
        cand = _limb_candidates(pose[None], idx, values, lo, hi)
        score = _score_finished(vox, skel, blobs, cand)[0]
        k = int(score.argmax())
        if float(score[k]) > best:
            best, pose = float(score[k]), cand[k]
    return pose, best, start


#: :func:`search_near_in_images`: each layer's first steps, along the floor (m), of the heading and of the joints
#: (rad), shrinking by ``shrink`` per layer; a body a step of a frame's walk or turn from its prediction.
NEAR_STEP_M = 0.08
NEAR_STEP_HEADING = 0.15
NEAR_STEP_RAD = 0.15
#: :func:`search_near_in_images`: a camera shows the body where at least this share of the body's volume lies in its
#: image and this share of that on its foreground.
NEAR_SEEN = 0.5


@dataclass(frozen=True)
class NearResult:
    """:func:`search_near_in_images`' answer: the best state ``angles (D,)``, its score in the images (0-1) and how
    many cameras show the body (:data:`NEAR_SEEN`)."""

    angles: torch.Tensor
    score: float
    cameras: int


def search_near_in_images(silhouettes: ViewSilhouettes, cameras_valid: torch.Tensor, skel: Skeleton,
                          blobs: BlobModel, predicted: torch.Tensor, generator: torch.Generator | None = None,
                          particles: int = 256, layers: int = 8, keep: int = 16, shrink: float = 0.7,
                          samples: int = SearchConfig.samples) -> NearResult:
    """The state near ``predicted (D,)`` (of ``skel``, placed as it is) that the cameras' foreground holds best: an
    annealed search, each child changing one part of the body from a kept parent (the place: along the floor, the
    heading and the tilt; the trunk; one limb), scored by :func:`image_terms`' two shares alone. For a body the
    observed volume no longer holds (it walked out to where fewer cameras see it than the grid asks for), which
    the voxels cannot track; the prediction keeps its depth along the few views' rays. 256 children a layer
    rather than 128 (docs/results.md, "Robustness", the image hold)."""
    views = _Views(silhouettes, cameras_valid)
    dev = views.fg.device
    names = list(skel.dof_names)
    place = [names.index(n) for n in ("root_tx", "root_ty", "root_rz")]
    groups = _dof_groups(skel).to(dev)  # group 0, the tilt, moves with the place
    groups[0, place] = 1.0
    steps = torch.full((skel.num_dofs,), NEAR_STEP_RAD, device=dev)
    steps[place[:2]], steps[place[2]] = NEAR_STEP_M, NEAR_STEP_HEADING
    pts = unit_ball_samples(samples, dtype=torch.float32, device=dev)
    lo, hi = skel.lower.float().to(dev), skel.upper.float().to(dev)
    semi0 = blobs.semi_axes.to(dev).float()

    def bodies(states):  # blobs (h, K, 3), (h, K, 3, 3), (h, K, 3), sample points (h, K, S, 3), volumes (h, K)
        c, R = blobs.ellipsoids(skel.forward(states.to(skel.lower)).bone_frames)
        c, R = c.float().to(dev), R.float().to(dev)
        semi = semi0[None].expand(c.shape[0], -1, -1)
        return c, R, semi, c[:, :, None] + torch.einsum("hkij,hksj->hksi", R, semi[:, :, None] * pts[None, None]), \
            semi.prod(-1)

    def scored(states):
        c, R, semi, q, vol = bodies(states)
        e, f = image_terms(c, R, semi, q, vol, views)
        return 2 * e * f / (e + f).clamp(min=1e-12)

    states = predicted.float().to(dev)[None]
    score = scored(states)
    step = 1.0
    for _ in range(layers):
        parent = torch.randint(states.shape[0], (particles,), generator=generator, device=dev)
        group = torch.randint(groups.shape[0], (particles,), generator=generator, device=dev)
        noise = torch.randn(particles, skel.num_dofs, generator=generator, device=dev) * step
        child = torch.maximum(torch.minimum(states[parent] + noise * steps * groups[group], hi), lo)
        states, score = torch.cat([states, child]), torch.cat([score, scored(child)])
        best = _top(score, keep)
        states, score = states[best], score[best]
        step *= shrink
    top = int(score.argmax())
    _, _, _, q, vol = bodies(states[top:top + 1])
    on, seen = _on_foreground(q, views)  # (C, 1, K)
    v = vol[0]
    seen_v, on_v = (seen[:, 0] * v).sum(-1), (on[:, 0] * v).sum(-1)  # (C,)
    shows = (seen_v >= NEAR_SEEN * v.sum()) & (on_v >= NEAR_SEEN * seen_v) & views.used
    return NearResult(states[top].to(predicted), float(score[top]), int(shows.sum()))


def _top(score: torch.Tensor, n: int) -> torch.Tensor:
    return score.topk(min(n, score.shape[0])).indices


def _top_both_ways(score: torch.Tensor, heading: torch.Tensor, n: int) -> torch.Tensor:
    """``n`` hypotheses: the best ceil(n / 2) facing within 90 deg of the best one's heading (the best among them),
    then the best floor(n / 2) facing away, then, where one side is short, the best of the other's rest. A walker's
    silhouette is nearly the same turned round, and the search otherwise settles in whichever basin the prior's
    coarse poses match best: both are kept at every stage where the images score the body (their knees and feet
    tell its front), not on a few views' hull, whose phantom volume the far basin then fits (docs/results.md,
    "Both headings kept, the race decided by the fit cost too"). One sort and no host synchronisation."""
    order = score.argsort(descending=True, stable=True)
    rel = torch.remainder(heading[order] - heading[order[0]] + math.pi, 2 * math.pi) - math.pi
    ahead = rel.abs() < 0.5 * math.pi
    rank = torch.where(ahead, ahead.cumsum(0), (~ahead).cumsum(0)) - 1  # each one's place on its own side
    spare = rank >= torch.where(ahead, n - n // 2, n // 2)  # beyond its side's share
    group = 2 * spare + (~ahead & ~spare)  # ahead in its share, away in its share, the rest by score
    return order[group.argsort(stable=True)[:n]]


def search_pose(obs: VoxelObservation, skel: Skeleton, blobs: BlobModel, config: SearchConfig = SearchConfig(),
                generator: torch.Generator | None = None, n: int = 3) -> SearchResult:
    """The ``n`` best whole-body states for the voxels of ``obs`` (module docstring).

    Args:
        obs: one frame's voxels (one person). skel, blobs: the body searched with (the template, or the tracked
            subject's for a re-acquisition with ``scale_range`` (1, 1)). generator: for the subsample and the
            annealed search's steps (on the voxels' device).

    Raises:
        InputError: no voxels.
    """
    if obs.num_voxels == 0:
        raise InputError("start search: no voxels")
    dev = obs.points.device
    skel = skel.to(dev)
    vox = _Voxels(obs, config.max_voxels, generator)
    hyp = _Hypotheses(skel, blobs, vox)
    samples = unit_ball_samples(config.samples, dtype=torch.float32, device=dev)
    headings = torch.arange(config.headings, dtype=torch.float32, device=dev) * (2 * math.pi / config.headings)
    total = 0

    def scored(poses, heading, scale, shift):
        nonlocal total
        c, R, a, state = hyp.place(poses, heading, scale, shift)
        total += poses.shape[0]
        return two_way_score(c, R, a, vox, samples), state

    def keep(score, heading):  # the hypotheses a stage passes on
        return _top(score, config.keep) if vox.views is None else _top_both_ways(score, heading, config.keep)

    # stage 1: the structured prior's legs x arms alike (also stooped over, where the images compare), and the real
    # captures' poses, each at every heading
    stooped = config.stooped and vox.views is not None and _images_compare(obs)
    base = pose_prior(skel, symmetric_arms=True).float()
    if stooped:
        bent = base.clone()
        for dof, value in STOOP.items():
            bent[:, skel.dof_names.index(dof)] += value
        base = torch.cat([base, skel.clamp(bent)])
    structured = base.shape[0] * headings.shape[0]  # the first hypotheses; the real poses' after them
    if config.real_poses:
        base = torch.cat([base, real_pose_prior(skel, config.prior_exclude).float()])
    P, Hh = base.shape[0], headings.shape[0]
    poses, heading = base.repeat_interleave(Hh, 0), headings.repeat(P)
    scale = hyp.initial_scale(poses, config.scale_range)
    shift = poses.new_zeros(poses.shape[0], 2)
    (score, *_), _ = scored(poses, heading, scale, shift)
    best = keep(score, heading)
    # stage 2: each kept hypothesis with every pair of the structured prior's arm poses (a structured pose's own
    # arms are one of them), and a kept real pose also as it is
    arms = pose_prior(skel).float()  # (legs x arm pairs, D), grouped by legs
    per_legs = len(ARM_POSES) ** 2
    names = list(skel.dof_names)
    arm_dofs = [names.index(f"{s}_{d}") for s in ("l", "r") for d in ("shoulder_flex", "shoulder_abd", "elbow_flex")]
    pairs = arms[:per_legs, arm_dofs]  # (A, 6) the arm poses (the first legs' block)
    real = best[best >= structured]
    kept = poses[real], heading[real], scale[real], score[real]
    poses = poses[best].repeat_interleave(per_legs, 0)
    poses[:, arm_dofs] = pairs.repeat(best.shape[0], 1)
    heading = heading[best].repeat_interleave(per_legs)
    scale = hyp.initial_scale(poses, config.scale_range)
    (score, *_), _ = scored(poses, heading, scale, poses.new_zeros(poses.shape[0], 2))
    poses, heading = torch.cat([kept[0], poses]), torch.cat([kept[1], heading])
    scale, score = torch.cat([kept[2], scale]), torch.cat([kept[3], score])
    shift = poses.new_zeros(poses.shape[0], 2)
    best = keep(score, heading)
    poses, heading, scale, shift, score = poses[best], heading[best], scale[best], shift[best], score[best]
    # stage 3: annealed search around them; each new hypothesis changes one part of the body (the place, the
    # trunk, one limb), as a partitioned search: a step in every joint at once mostly makes a hypothesis worse
    lo, hi = skel.lower.float(), skel.upper.float()

    def sweep(poses, heading, scale, shift, score):
        # each limb in turn over its grid, every hypothesis keeping the best of its own (itself included); each
        # candidate sized as the first stages size a pose (its top at the voxels' top), since a leg's bend or a
        # raised arm changes the body's height
        H, rows = poses.shape[0], torch.arange(poses.shape[0], device=dev)
        for idx, values in _limb_grids(skel, stooped):
            V = values.shape[0]
            cand = _limb_candidates(poses, idx, values, lo, hi)
            c_scale = hyp.initial_scale(cand, config.scale_range)
            (c_score, *_), _ = scored(cand, heading.repeat_interleave(V), c_scale, shift.repeat_interleave(V, 0))
            top, pick = c_score.view(H, V).max(1)
            better = top > score
            poses = torch.where(better[:, None], cand.view(H, V, -1)[rows, pick], poses)
            scale = torch.where(better, c_scale.view(H, V)[rows, pick], scale)
            score = torch.where(better, top, score)
        return poses, scale, score

    groups = _dof_groups(skel)  # (G, D) bool; group 0: the place (heading, shift, scale, tilt)
    if config.sweep and (vox.views is not None or config.sweep_voxels):
        poses, scale, score = sweep(poses, heading, scale, shift, score)
    step = 1.0
    for _ in range(config.layers):
        m = config.particles
        parent = torch.randint(poses.shape[0], (m,), generator=generator, device=dev)
        group = torch.randint(groups.shape[0], (m,), generator=generator, device=dev)
        noise = torch.randn(m, skel.num_dofs + 4, generator=generator, device=dev) * step
        child = poses[parent] + STEP_RAD * noise[:, :skel.num_dofs] * groups[group]
        child = torch.maximum(torch.minimum(child, hi), lo)
        place = (group == 0).float()
        c_heading = heading[parent] + 0.35 * noise[:, -4] * place
        c_scale = (scale[parent] * torch.exp(0.04 * noise[:, -3] * place)).clamp(*config.scale_range)
        c_shift = shift[parent] + 0.05 * noise[:, -2:] * place[:, None]
        (c_score, *_), _ = scored(child, c_heading, c_scale, c_shift)
        poses = torch.cat([poses, child])
        heading, scale = torch.cat([heading, c_heading]), torch.cat([scale, c_scale])
        shift, score = torch.cat([shift, c_shift]), torch.cat([score, c_score])
        best = keep(score, heading)
        poses, heading, scale, shift, score = poses[best], heading[best], scale[best], shift[best], score[best]
        step *= config.shrink
    best = _top(score, n)
    (score, explained, filled, outside), state = scored(poses[best], heading[best], scale[best], shift[best])
    total -= best.shape[0]  # re-scored, not new
    return SearchResult(state, scale[best], score, explained, filled, outside, total)
