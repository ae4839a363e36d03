"""Marker-based tracking by an annealed particle filter (Canton-Ferrer et al. 2010; Deutscher & Reid's annealing).

Per frame: the particles (states of the skeleton) start from the last estimate; each of ``layers`` layers
perturbs them by a truncated Gaussian inside the joint limits (its spread shrinking layer by layer), weighs them by
``exp(-beta * cost)`` with ``beta`` set for a target survival rate, and resamples. The cost of a state is the
symmetric epipolar distance between each model marker's projection in one view and the marker's detections in
another (the best of the candidates, capped at an outlier threshold; kornia's fundamental matrices), summed over
markers and ordered pairs of views. The estimate is the weighted mean of the last layer, polished by
Levenberg-Marquardt on the reprojection error of the detections nearest its markers (the pose of least error
under the detector's pixel noise; ``APFConfig.polish``). Several subjects (sequences) are tracked in lockstep by
one filter: their particles a batch beside each other, their marker sets and rigs padded. No I/O here; one frame is
a few large tensor operations over the subjects and their particles.

Detections are compared in each camera's undistorted (pinhole) pixels, where the epipolar geometry holds; the cost
is :mod:`torchtrack.tracking.epipolar`'s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.markers.model import MarkerSet
from torchtrack.skeleton.model import LockstepBodies, Skeleton
from torchtrack.tracking.epipolar import (FAR_PX, EpipolarCost, ReprojectionCost, fundamental_matrices,
                                         projection_matrices)

__all__ = ["APFConfig", "MarkerAPF", "annealing_beta", "resample", "truncated_normal"]


@dataclass(frozen=True)
class APFConfig:
    """The filter's settings.

    Attributes:
        particles: particles per layer. layers: annealing layers per frame (the paper's best: 5).
        survival: the survival rate each layer's ``beta`` is set for (effective sample size / particles).
        outlier_rad: a marker's epipolar distance to a view's detections counts at most this much, as an angle
            (radians; times each rig's median focal length in pixels): a detection farther off is another marker's
            or a false one, or the body model cannot reach it (the polish's reprojection error is capped the same).
            An angle, not pixels, so that one setting holds for any camera's resolution (0.03: 16 px at 640 x 480,
            50 px at 1920 x 1088).
        root_m, root_rad, joint_rad: the first layer's perturbation (standard deviation) of the root's translation,
            its rotation and every joint angle; ``shrink``: each later layer's, as a factor of the one before.
        partitioned: each limb's joints resampled by the limb's own markers (the trunk's by all of them), not whole
            particles by the total cost alone.
        velocity: the share of the last frame's motion the prediction carries on (0: none).
        polish_steps: Levenberg-Marquardt iterations from the filter's estimate (0: none), on ``polish``: the
            reprojection error of each marker's nearest candidate in each view (``"reprojection"``), or the
            layers' epipolar cost (``"epipolar"``), whose least weighs an error along a pair's epipolar line not
            at all there (:class:`~torchtrack.tracking.epipolar.ReprojectionCost`).
        refit_m: after a first track, each marker's bone and offset are fitted again on every frame's triangulated
            markers within this distance of the track's (the first seconds alone, often still, place them poorly),
            and the capture is tracked again with them (0: one track; :mod:`torchtrack.markers.track`). 0.1 m is
            what the lost-track test calls far (``LOST_M``): nearer, a detection is taken for the marker's.
        measured_m, measured_views, smooth_s, fill_s: each output marker is placed where its detections
            triangulate it (``measured_views`` views agreeing) within ``measured_m`` of the body's marker, its
            offset from the body's smoothed in time (a Gaussian of ``smooth_s`` seconds), and filled from the body's
            marker and the offsets measured within ``fill_s`` seconds where not (0 m: the body's markers alone;
            :func:`~torchtrack.markers.gaps.measured_markers`). The rigid body cannot follow skin that slides on
            the bones; its joint angles are the track either way.
        The figures behind these values: docs/results.md, "Marker-based capture".
    """

    particles: int = 500
    layers: int = 5
    survival: float = 0.5
    outlier_rad: float = 0.03
    root_m: float = 0.02
    root_rad: float = 0.03
    joint_rad: float = 0.05
    shrink: float = 0.5
    partitioned: bool = True
    velocity: float = 0.8
    polish_steps: int = 20
    polish: str = "reprojection"
    refit_m: float = 0.1
    measured_m: float = 0.05
    measured_views: int = 2
    smooth_s: float = 1 / 30
    fill_s: float = 0.5

    def __post_init__(self) -> None:
        if (self.particles < 2 or self.layers < 1 or not 0 < self.survival < 1
                or not 0 < self.outlier_rad < math.inf):
            raise InputError(f"APFConfig: particles >= 2, layers >= 1, survival in (0, 1), finite outlier_rad > 0; "
                             f"got {self}")
        if self.polish not in ("reprojection", "epipolar"):
            raise InputError(f"APFConfig: polish is 'reprojection' or 'epipolar', got {self.polish!r}")
        if min(self.root_m, self.root_rad, self.joint_rad, self.refit_m) < 0 or not 0 < self.shrink <= 1:
            raise InputError(f"APFConfig: perturbations >= 0 and shrink in (0, 1]; got {self}")
        if self.measured_m < 0 or self.measured_views < 2 or min(self.smooth_s, self.fill_s) < 0:
            raise InputError(f"APFConfig: measured_m >= 0, measured_views >= 2, smooth_s and fill_s >= 0; got {self}")


#: The polish's forward-difference step (m for the root's translation, rad for angles), and the relative fall of
#: the cost below which it stops: a thousandth of a cost that is about the frame's residuals (100-300) times the
#: pixel noise's variance is 0.1-0.3 of one variance (more where outliers sit at the cap), a change of pose well
#: inside the estimate's own uncertainty (a chi-square change below 1), which the slow last steps on the outlier
#: cap's edges only creep along.
FD_STEP, POLISH_TOL = 1e-6, 1e-3
#: The least exponent a particle's weight ``exp(-beta * cost)`` is taken at (relative to the best particle's 1): below
#: about -87 float32's exp underflows into subnormal numbers (float64's below about -708), which a CPU computes about
#: a hundred times slower, and a weight of e^-80 (2e-35) is as good as none beside the best particle's.
LEAST_EXPONENT = -80.0
#: The polish's dampings a step tries (each ten times the one before), all in one batch.
DAMPING_TRIES = 4
#: On a CPU the layers anneal at most about this many particles at once (subjects in lockstep in chunks, one
#: subject's many particles weighed in chunks): a layer's tensors then stay in memory the allocator reuses, where
#: those of 16 subjects' 1000 particles at once (50 MB each) were fresh pages every time, 2x slower a particle
#: (docs/results.md, "Marker-based capture"). A GPU takes them all at once.
CPU_CHUNK_STATES = 1000
#: The limbs whose joints the filter resamples by their own markers: name prefixes of their DOFs and bones.
LIMBS = (("l_shoulder", "l_elbow", "l_wrist", "l_upperarm", "l_forearm", "l_hand"),
         ("r_shoulder", "r_elbow", "r_wrist", "r_upperarm", "r_forearm", "r_hand"),
         ("l_hip", "l_knee", "l_ankle", "l_thigh", "l_shank", "l_foot"),
         ("r_hip", "r_knee", "r_ankle", "r_thigh", "r_shank", "r_foot"))


def _part(name: str) -> int:
    """The body part of a DOF or bone name: 1 + its limb in ``LIMBS``, or 0 (root, trunk, head)."""
    for g, prefixes in enumerate(LIMBS):
        if name.startswith(prefixes):
            return g + 1
    return 0


def _floored_exp(x: torch.Tensor) -> torch.Tensor:
    """``exp(max(x, LEAST_EXPONENT))``: the particles' weights, none of them subnormal (:data:`LEAST_EXPONENT`)."""
    return torch.exp(x.clamp(min=LEAST_EXPONENT))


def annealing_beta(cost: torch.Tensor, survival: float, stages: int = 3, points: int = 8) -> torch.Tensor:
    """Per row of ``cost (..., N)``, the ``beta`` whose weights ``exp(-beta * (cost - min))`` have an effective
    sample size of ``survival`` times N; the survival rate falls as beta grows, so each of ``stages`` rounds
    evaluates it at ``points`` values of log beta in one tensor operation and keeps the bracket where it crosses
    ``survival``. The first bracket starts where the rate is surely above ``survival`` (every weight at least
    ``survival^(1/2)``: beta = -log(survival) / (2 max(cost - min))) and spans 30 in log beta (a factor of 1e13:
    then only the costs tied with the least keep a weight), the last (30 / (points - 1)^stages wide, 0.09 by
    default) is closed by taking log rate as linear in log beta across it: the rate within about 1e-3 of
    ``survival``.
    The weights are summed in float32 (half float64's cost; the rate's rounding is far below that), each at least
    ``exp(LEAST_EXPONENT)`` (:func:`_floored_exp`). Returns ``(...,)`` float64; 0 where a row's costs are all
    equal."""
    if not 0 < survival < 1:
        raise InputError(f"annealing_beta: survival must be in (0, 1), got {survival}")
    c = (cost - cost.amin(-1, keepdim=True)).double()  # (..., N)
    c32 = c.float()
    n = c.shape[-1]
    top = torch.where(torch.isfinite(c), c, 0.0).amax(-1)  # an infinite cost gets only the floor's weight
    # (at most 50: beta then stays within float32's range, and a row whose costs all lie within 1e-22 of each
    # other keeps every weight near 1 anyway)
    lo = torch.log(-math.log(survival) / (2 * top.clamp(min=1e-300))).clamp(max=50.0)
    hi = lo + 30.0
    steps = torch.linspace(0.0, 1.0, points, dtype=c.dtype, device=c.device)
    for _ in range(stages):
        grid = lo[..., None] + (hi - lo)[..., None] * steps  # (..., P) log beta
        w = _floored_exp(-grid.exp().float()[..., None] * c32[..., None, :])  # (..., P, N)
        rate = (w.sum(-1) ** 2 / (n * w.square().sum(-1))).double()  # (..., P), falling along P
        k = (rate > survival).sum(-1, keepdim=True).clamp(1, points - 1)  # the first point at or below
        lo, hi = grid.gather(-1, k - 1)[..., 0], grid.gather(-1, k)[..., 0]
        r_lo, r_hi = rate.gather(-1, k - 1)[..., 0], rate.gather(-1, k)[..., 0]
    # within the last bracket, log rate taken as linear in log beta
    drop = (r_lo.log() - r_hi.log()).clamp(min=1e-12)
    frac = ((r_lo.log() - math.log(survival)) / drop).clamp(0.0, 1.0)
    return torch.where(top > 0, (lo + frac * (hi - lo)).exp(), 0.0)


Generators = torch.Generator | Sequence[torch.Generator]


def _rand(shape: tuple[int, ...], generator: Generators, device: torch.device, normal: bool = False,
          dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Uniform (or, with ``normal``, standard normal) draws of ``shape``; with a sequence of generators, row q of the
    leading axis from generator q (a subject's draws then do not depend on the others tracked in lockstep with
    it)."""
    draw = torch.randn if normal else torch.rand
    if isinstance(generator, torch.Generator):
        return draw(shape, generator=generator, device=device, dtype=dtype)
    if len(generator) != shape[0]:
        raise InputError(f"{len(generator)} generators for draws of shape {tuple(shape)}")
    return torch.stack([draw(shape[1:], generator=g, device=device, dtype=dtype) for g in generator])


def resample(weights: torch.Tensor, generator: Generators) -> torch.Tensor:
    """Indices ``(..., N)`` drawn by systematic resampling from each row of unnormalised ``weights (..., N)`` (one
    uniform offset per row; ``generator``: one, or one per leading row)."""
    w = weights.double()
    N = w.shape[-1]
    cdf = w.cumsum(-1) / w.sum(-1, keepdim=True)
    u = (_rand((*w.shape[:-1], 1), generator, w.device) + torch.arange(N, device=w.device, dtype=torch.float64)) / N
    return torch.searchsorted(cdf.contiguous(), u.contiguous()).clamp(max=N - 1)


def truncated_normal(mean: torch.Tensor, std: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor,
                     generator: Generators) -> torch.Tensor:
    """Samples of N(mean, std^2) truncated to [lower, upper], elementwise (``mean (..., D)``, the others
    broadcasting); exact, no rejection loop: a plain normal draw where it falls inside, the inverse CDF of the
    truncated law where it does not (a mixture of the two is the truncated law itself). On a CPU the inverse CDF,
    most of the cost, runs only where it is needed. ``std`` 0 gives ``mean`` clamped. ``generator``: one, or one per
    leading row of ``mean``. In ``mean``'s dtype, the inverse CDF in float64."""
    dt = mean.dtype
    s = std.to(dt).expand_as(mean)
    lo, hi = lower.to(dt).expand_as(mean), upper.to(dt).expand_as(mean)
    # the draws in float32 (a fifth of float64's normal draws' cost; their resolution is far below the spreads')
    x = mean + s * _rand(mean.shape, generator, mean.device, normal=True, dtype=torch.float32).to(dt)
    u = _rand(mean.shape, generator, mean.device, dtype=torch.float32)
    out = (x < lo) | (x > hi)

    def inverse(m, s, lo, hi, u):  # the truncated law's inverse CDF at u, in float64 (its tails need it)
        m, s, lo, hi, u = (v.double() for v in (m, s, lo, hi, u))
        safe = s > 0
        s1 = torch.where(safe, s, 1.0)
        a = torch.special.ndtr((lo - m) / s1)
        b = torch.special.ndtr((hi - m) / s1)
        v = (a + (b - a) * u).clamp(torch.finfo(torch.float64).tiny, 1 - 1e-16)
        return torch.where(safe, m + s1 * torch.special.ndtri(v), m).to(dt)

    if mean.device.type == "cpu":
        idx = out.nonzero(as_tuple=True)
        x[idx] = inverse(mean[idx], s[idx], lo[idx], hi[idx], u[idx])
    else:  # no host synchronisation: every element's inverse, taken where needed
        x = torch.where(out, inverse(mean, s, lo, hi, u), x)
    return torch.minimum(torch.maximum(x, lo), hi)


class MarkerAPF:
    """The annealed particle filter of one subject, or of Q subjects in lockstep: one frame of all of them is the
    same few large tensor operations, the subjects a batch dimension beside their particles.

    Args:
        skeleton: the subject's skeleton (its bone lengths), or a sequence of Q of one chain. marker_set: its
            markers, or Q marker sets (their numbers may differ). rig: the cameras, or Q rigs (the same).
        config: the filter's settings, every subject's. generator: every random draw's source, or one per subject
            (each subject's track then the same whichever others it is tracked with).
    """

    def __init__(self, skeleton: Skeleton | Sequence[Skeleton], marker_set: MarkerSet | Sequence[MarkerSet],
                 rig: nn.Module | Sequence[nn.Module], config: APFConfig = APFConfig(),
                 generator: Generators | None = None) -> None:
        many = isinstance(skeleton, (list, tuple))
        self.skeletons = list(skeleton) if many else [skeleton]
        self.marker_sets = list(marker_set) if many else [marker_set]
        self.rigs = list(rig) if many else [rig]
        Q = len(self.skeletons)
        if not Q or len(self.marker_sets) != Q or len(self.rigs) != Q:
            raise InputError(f"MarkerAPF: give as many marker sets and rigs as skeletons, at least one; got "
                             f"{Q}, {len(self.marker_sets)}, {len(self.rigs)}")
        self.config = config
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        first = self.skeletons[0]
        D, dev = first.num_dofs, first.lower.device  # everything on the skeletons' device
        self.bodies32 = LockstepBodies(self.skeletons, torch.float32, dev)  # the layers' forward kinematics
        self.bodies64 = LockstepBodies(self.skeletons, torch.float64, dev)  # the polish's and the estimates'
        # the polish's Jacobian in closed form: each DOF's link, axis and kind, and the markers it moves
        self.dof_link, self.dof_axis, self.dof_turns = self.bodies64.dof_axes()
        # the subjects' markers and cameras, padded to the most of any (a padded marker has no detections, a
        # padded view no epipolar geometry: neither adds to a cost)
        self.num_markers = [m.num_markers for m in self.marker_sets]
        M, C = max(self.num_markers), max(r.num_cameras for r in self.rigs)
        self.bone = torch.zeros(Q, M, dtype=torch.long, device=dev)
        self.offset = torch.zeros(Q, M, 3, dtype=torch.float64, device=dev)
        self.marker_part = torch.zeros(Q, M, dtype=torch.long, device=dev)
        self.marker_mask = torch.zeros(Q, M, dtype=torch.bool, device=dev)
        self.P = torch.zeros(Q, C, 3, 4, dtype=torch.float64, device=dev)
        self.F = torch.zeros(Q, C, C, 3, 3, dtype=torch.float64, device=dev)
        for q, (skel, mset, r) in enumerate(zip(self.skeletons, self.marker_sets, self.rigs)):
            m, c = mset.num_markers, r.num_cameras
            self.bone[q, :m] = mset.bone.to(dev)
            self.offset[q, :m] = mset.offset.to(dev, torch.float64)
            self.marker_part[q, :m] = torch.tensor([_part(skel.bone_names[b]) for b in mset.bone.tolist()])
            self.marker_mask[q, :m] = True
            Pq = projection_matrices(r).to(dev, torch.float64)
            self.P[q] = Pq[:1].expand(C, 3, 4)
            self.P[q, :c] = Pq
            self.F[q, :c, :c] = fundamental_matrices(r).to(dev)
        self.subject = torch.arange(Q, device=dev)[:, None]
        focal = torch.stack([r.K[:, :2].diagonal(dim1=-2, dim2=-1).double().median().to(dev) for r in self.rigs])
        self.outlier_px = config.outlier_rad * focal  # (Q,) each subject's outlier cap in its rig's pixels
        self.far_px = max(FAR_PX, 10.0 * float(self.outlier_px.max()))  # EpipolarCost's, checked once here
        moves = self.bodies64.descends(self.dof_link)  # (F, D)
        self.marker_moves = moves[self.bodies64.bone_index[self.bone]].to(torch.float64)  # (Q, M, D)
        std = torch.full((D,), config.joint_rad, dtype=torch.float64, device=dev)
        std[:3], std[3:6] = config.root_m, config.root_rad
        self.std = std
        self.lower = torch.stack([s.lower.to(dev, torch.float64) for s in self.skeletons])  # (Q, D)
        self.upper = torch.stack([s.upper.to(dev, torch.float64) for s in self.skeletons])
        # the body's parts: each limb's joints and the markers on its bones (the trunk, root and head: part 0)
        self.dof_part = torch.tensor([_part(n) for n in first.dof_names], device=dev)
        self.states: torch.Tensor | None = None  # (Q, D) the last estimates
        self.previous: torch.Tensor | None = None  # (Q, D) the ones before
        self.spreads = torch.full((Q,), math.nan, dtype=torch.float64)

    @property
    def skeleton(self) -> Skeleton:
        """The first subject's skeleton (the one of a single-subject filter)."""
        return self.skeletons[0]

    @property
    def marker_set(self) -> MarkerSet:
        """The first subject's marker set."""
        return self.marker_sets[0]

    @property
    def state(self) -> torch.Tensor | None:
        """The first subject's last estimate ``(D,)`` (the one of a single-subject filter)."""
        return None if self.states is None else self.states[0]

    @property
    def spread(self) -> float:
        """The first subject's particle spread (m; :meth:`step`)."""
        return float(self.spreads[0])

    def reset(self, angles: torch.Tensor, subject: int | None = None) -> None:
        """Start from the states ``angles (Q, D)``, or one subject's (``angles (D,)``; without ``subject``: the
        first, or every subject where the filter has one)."""
        Q, D = len(self.skeletons), self.skeletons[0].num_dofs
        angles = angles.detach().to(self.std)
        if subject is None and angles.dim() == 1 and Q == 1:
            subject = 0
        if subject is None:
            check_shape(angles, (Q, D), "angles")
            self.states = angles.clone()
        else:
            check_shape(angles, (D,), "angles")
            if self.states is None:
                if Q > 1:
                    raise InputError("MarkerAPF.reset: give every subject's start (Q, D) first")
                self.states = angles[None].clone()
            one = torch.arange(Q, device=angles.device)[:, None] == subject  # out of place: estimates handed out
            self.states = torch.where(one, angles, self.states)             # earlier stay as they were
            if self.previous is not None:
                self.previous = torch.where(one, angles, self.previous)
        if subject is None or self.previous is None:
            self.previous = self.states.clone()

    def clamp(self, angles: torch.Tensor) -> torch.Tensor:
        """Each subject's states ``(Q, ..., D)`` clamped to its joint limits."""
        shape = (angles.shape[0],) + (1,) * (angles.dim() - 2) + (angles.shape[-1],)
        return torch.clamp(angles, self.lower.view(shape).to(angles), self.upper.view(shape).to(angles))

    def hold(self, held: torch.Tensor | None = None) -> None:
        """Frames without detections: the subjects ``held (Q,)`` (default: all) keep their states, and their next
        frame predicts without velocity."""
        if self.states is not None:
            held = torch.ones(len(self.skeletons), dtype=torch.bool) if held is None else held
            self.previous = torch.where(held.to(self.states.device)[:, None], self.states, self.previous)

    def markers(self, angles: torch.Tensor, subject: int = 0) -> torch.Tensor:
        """One subject's states ``(B, D)`` -> (B, M, 3) its model markers, in the states' dtype."""
        mset = self.marker_sets[subject]
        return mset.positions_last(*self.skeletons[subject].bone_poses_last(angles)).permute(2, 0, 1)

    def markers_all(self, angles: torch.Tensor, subjects: slice | torch.Tensor = slice(None)) -> torch.Tensor:
        """Every subject's states ``(Q, N, D)`` -> (Q, M, 3, N) their model markers, states last (padded markers:
        the first bone's origin), float32 or float64 as the states; ``subjects``: the states are those of these
        subjects (a slice or indices)."""
        bodies = self.bodies32 if angles.dtype == torch.float32 else self.bodies64
        R, t = bodies(angles.to(bodies.origins.dtype), subjects)  # (nb, 3, 3, Q, N), (nb, 3, Q, N)
        return self._place(R, t, subjects)

    def _place(self, R: torch.Tensor, t: torch.Tensor, subjects: slice | torch.Tensor = slice(None)
               ) -> torch.Tensor:
        """The bones' rotations ``(nb, 3, 3, Q, N)`` and origins ``(nb, 3, Q, N)`` of the ``subjects`` -> their
        markers ``(Q, M, 3, N)`` (:meth:`markers_all`)."""
        bone, offset = self.bone[subjects], self.offset[subjects]
        nb, Q, M, N = R.shape[0], *bone.shape, R.shape[-1]
        rows = (bone * Q + self.subject[:Q]).view(-1)  # each marker's row of (bone, subject) pairs
        Rm = R.movedim(3, 1).reshape(nb * Q, 3, 3, N).index_select(0, rows).view(Q, M, 3, 3, N)
        tm = t.movedim(2, 1).reshape(nb * Q, 3, N).index_select(0, rows).view(Q, M, 3, N)
        o = offset.to(Rm)[:, :, None, :, None]  # (Q, M, 1, 3, 1)
        return tm.addcmul_(Rm[:, :, :, 0], o[..., 0, :]).addcmul_(Rm[:, :, :, 1], o[..., 1, :]).addcmul_(
            Rm[:, :, :, 2], o[..., 2, :])

    def _layer_costs(self, score: EpipolarCost, x: torch.Tensor, subjects: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """The per-marker costs ``(q, M, N)`` of the particles ``x (q, N, D)`` of the ``subjects (q,)`` by their
        ``score``, and their markers ``(q, M, 3, N)``; a CPU's many particles in chunks (:data:`CPU_CHUNK_STATES`)."""
        N = x.shape[1]
        if x.device.type != "cpu" or N <= CPU_CHUNK_STATES:
            pts = self.markers_all(x, subjects)
            return score.cost(pts, per_marker=True), pts
        per = x.new_empty(x.shape[0], self.bone.shape[1], N)
        pts = x.new_empty(x.shape[0], self.bone.shape[1], 3, N)
        for n in range(0, N, CPU_CHUNK_STATES):
            chunk = slice(n, n + CPU_CHUNK_STATES)
            pts[..., chunk] = self.markers_all(x[:, chunk], subjects)
            per[..., chunk] = score.cost(pts[..., chunk], per_marker=True)
        return per, pts

    def _anneal(self, detections: torch.Tensor, x: torch.Tensor, generator: Generators, subjects: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The annealing layers of the ``subjects (q,)`` from their particles ``x (q, N, D)`` (each the predicted
        state) against their ``detections`` (float32) -> the last layer's particles ``(q, N, D)`` (float32), weights
        ``(q, N)`` and markers ``(q, M, 3, N)`` (float32)."""
        cfg = self.config
        q, N, D = x.shape
        G = len(LIMBS) + 1
        std, lower, upper = self.std, self.lower[subjects, None], self.upper[subjects, None]
        part = self.dof_part if cfg.partitioned else torch.zeros_like(self.dof_part)  # the row each DOF takes
        by_part = self.marker_part[subjects, :, None].expand(q, -1, N)
        score = EpipolarCost(detections, self.P[subjects], self.F[subjects], self.outlier_px[subjects], self.far_px)
        x = x.float()  # the particles in float32 (a ten-millionth of a radian: far below any spread)
        for _ in range(cfg.layers):
            x = truncated_normal(x, std, lower, upper, generator)
            per, pts = self._layer_costs(score, x, subjects)
            per = per.double()  # (q, M, N)
            parts = per.new_zeros(q, G, N).scatter_add_(1, by_part, per)  # (q, G, N)
            # row 0 weighs whole particles by the total cost; with ``partitioned``, row g weighs limb g's joints by
            # the limb's own markers (the trunk's as the whole particle drew them)
            costs = torch.cat([parts.sum(1, keepdim=True), parts[:, 1:]], 1)
            if not cfg.partitioned:
                costs = costs[:, :1]
            W = _floored_exp(-annealing_beta(costs, cfg.survival)[..., None] * (costs - costs.amin(-1, keepdim=True)))
            keep, w = x, W[:, 0]
            idx = resample(W, generator)  # (q, rows, N): each row's draw of whole particles
            x = keep.gather(1, idx[:, part].mT)  # each DOF from its part's row: keep[q, idx[q, part[d], n], d]
            std = std * cfg.shrink
        return keep, w / w.sum(-1, keepdim=True), pts

    def _chunks(self, active: torch.Tensor, N: int) -> list[torch.Tensor]:
        """The subjects annealed together, of those ``active (Q,)``: all of them on a GPU; on a CPU, as many as make
        :data:`CPU_CHUNK_STATES` particles (at least one)."""
        which = active.nonzero()[:, 0]
        if not len(which):
            return []
        step = len(which) if which.device.type != "cpu" else max(1, CPU_CHUNK_STATES // N)
        return list(which.split(step))

    def pad_detections(self, detections: Sequence[torch.Tensor], candidates: int | None = None) -> torch.Tensor:
        """Each subject's detections ``(T_q, C_q, M_q, K_q, 2)`` in pinhole pixels -> ``(T, Q, C, M, K, 2)``, padded
        with NaN to the longest, the most views and markers, and ``candidates`` (default: the most of any)
        candidates (:meth:`step_all`'s layout)."""
        if len(detections) != len(self.skeletons):
            raise InputError(f"MarkerAPF.pad_detections: {len(detections)} subjects' detections for "
                             f"{len(self.skeletons)} subjects")
        T = max(d.shape[0] for d in detections)
        K = max(d.shape[3] for d in detections) if candidates is None else candidates
        Q, C, M = self.P.shape[0], self.P.shape[1], self.bone.shape[1]
        out = torch.full((T, Q, C, M, K, 2), math.nan, dtype=detections[0].dtype, device=detections[0].device)
        for q, d in enumerate(detections):
            out[:d.shape[0], q, :d.shape[1], :d.shape[2], :d.shape[3]] = d
        return out

    def _links(self, angles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every subject's states ``(Q, N, D)`` (float64) -> every link's rotation ``(F, 3, 3, Q, N)`` and origin
        ``(F, 3, Q, N)``, and the markers ``(Q, M, 3, N)``."""
        R, t = self.bodies64.links(angles)
        index = self.bodies64.bone_index
        return R, t, self._place(R[index], t[index])

    def _marker_jacobian(self, R: torch.Tensor, t: torch.Tensor, markers: torch.Tensor) -> torch.Tensor:
        """The markers' derivatives by the state ``(Q, M, 3, D)`` at one state of each subject, from its links'
        rotations ``R (F, 3, 3, Q)``, origins ``t (F, 3, Q)`` and its ``markers (Q, M, 3)``: a turning DOF moves a
        marker of its subtree by ``w x (x - o)`` (``w`` its world axis, ``o`` its link's origin), a sliding one by
        ``w``."""
        w = torch.einsum("dijq,dj->qdi", R[self.dof_link], self.dof_axis.to(R))  # (Q, D, 3)
        lever = markers[:, :, None] - t[self.dof_link].permute(2, 0, 1)[:, None]  # (Q, M, D, 3)
        J = torch.where(self.dof_turns[:, None], torch.linalg.cross(w[:, None].expand_as(lever), lever), w[:, None])
        return (J * self.marker_moves[..., None]).transpose(-1, -2)

    def _polish(self, angles: torch.Tensor, score: EpipolarCost | ReprojectionCost, going: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Levenberg-Marquardt on the cost's residuals from the filter's estimates ``(Q, D)`` (of the subjects
        ``going (Q,)``), within the joint limits; each subject damps and stops on its own. Returns the states
        ``(Q, D)`` and their markers ``(Q, M, 3)``, in float64. The Jacobian is the residuals' derivatives by each
        marker's position (forward differences: a residual depends on its own marker's position alone, so three
        moves of all markers give them) times the markers' derivatives by the state in closed form
        (:meth:`_marker_jacobian`), from the links of the step's accepted trial: one forward kinematics a step, of
        the trials. Hand-written over scipy's ``least_squares`` because a step is kept only where the true cost falls
        (each marker's nearest candidate and the outlier cap change under it): scipy's LM and TRF stalled on such
        frames (docs/results.md, "Marker-based capture")."""
        theta = angles.detach().double()
        Q, D = theta.shape
        dev = theta.device
        C, M = self.P.shape[1], self.bone.shape[1]
        moves = torch.cat([torch.zeros(3, 1, dtype=theta.dtype, device=dev),
                           torch.eye(3, dtype=theta.dtype, device=dev) * FD_STEP], 1)  # (3, 4): none, x, y, z
        eye = torch.eye(D, dtype=theta.dtype, device=dev)
        tries = 10.0 ** torch.arange(DAMPING_TRIES, dtype=theta.dtype, device=dev)  # each step's dampings, in turn
        lam = torch.full((Q,), 1e-3, dtype=theta.dtype, device=dev)
        going = going.to(dev).clone()
        R, t, X = self._links(theta[:, None])  # (F, 3, 3, Q, 1), (F, 3, Q, 1), (Q, M, 3, 1)
        R, t, X = R[..., 0], t[..., 0], X[..., 0]
        cost = score.cost(X[..., None])[:, 0]  # (Q,)
        rows = torch.arange(Q, device=dev)
        for _ in range(self.config.polish_steps):
            if not bool(going.any()):
                break
            r, _ = score.residuals(X[..., None] + moves)  # (Q, 4, R), the estimate's nearest candidates
            # by the marker's x, y, z: (Q, 3, C, M, each view's and marker's residuals)
            dr = ((r[:, 1:] - r[:, :1]) / FD_STEP).view(Q, 3, C, M, -1)
            J = torch.einsum("qkcma,qmkd->qdcma", dr, self._marker_jacobian(R, t, X)).reshape(Q, D, -1)
            A, g = J @ J.mT, (J @ r[:, 0, :, None])[..., 0]
            # every damping tried at once; each subject takes the least one whose cost falls, as trying them in
            # turn would (a subject none of them lowers stops)
            lams = lam[:, None] * tries  # (Q, T)
            damping = lams[..., None, None] * (torch.diag_embed(A.diagonal(dim1=-2, dim2=-1)) + 1e-9 * eye)[:, None]
            trial = self.clamp(theta[:, None] + torch.linalg.solve(A[:, None] + damping, -g[:, None, :, None])[..., 0])
            Rt, tt, Xt = self._links(trial)  # (F, 3, 3, Q, T), (F, 3, Q, T), (Q, M, 3, T)
            c = score.cost(Xt)  # (Q, T)
            ok = going[:, None] & (c < cost[:, None])
            moved = ok.any(1)
            k = ok.to(torch.uint8).argmax(1)  # the first that fell
            theta = torch.where(moved[:, None], trial[rows, k], theta)
            R = torch.where(moved, Rt[..., rows, k], R)
            t = torch.where(moved, tt[..., rows, k], t)
            X = torch.where(moved[:, None, None], Xt[rows, ..., k], X)
            trial_cost = torch.where(moved, c[rows, k], cost)
            converged = cost - trial_cost < POLISH_TOL * cost
            cost = trial_cost
            lam = torch.where(moved, (lams[rows, k] / 10.0).clamp(min=1e-7), lam)
            going = moved & ~converged
        return theta, X

    def step(self, detections: torch.Tensor) -> torch.Tensor:
        """One frame of a single-subject filter: ``detections (C, M, K, 2)`` in pinhole pixels
        (:func:`~torchtrack.tracking.epipolar.pinhole_pixels`) -> the estimate ``(D,)`` (:meth:`step_all`)."""
        if len(self.skeletons) != 1:
            raise InputError(f"MarkerAPF.step: the filter has {len(self.skeletons)} subjects; use step_all")
        return self.step_all(detections[None])[0]

    def step_all(self, detections: torch.Tensor, active: torch.Tensor | None = None) -> torch.Tensor:
        """One frame of every subject: ``detections (Q, C, M, K, 2)`` in pinhole pixels (:meth:`pad_detections`)
        -> the estimates ``(Q, D)``. Subjects not ``active (Q,)`` (default: all are) are held (:meth:`hold`).
        :attr:`spreads` ``(Q,)`` is the last layer's weighted RMS distance of the particles' markers from the
        estimate's (m), the paper's lost-track signal (it stays small where the whole cloud follows a wrong pose:
        :mod:`torchtrack.markers.track` tests the estimate against the triangulated markers instead)."""
        if self.states is None:
            raise InputError("MarkerAPF.step: no state yet; call reset() with a start pose")
        cfg, gen = self.config, self.generator
        Q, D = self.states.shape
        N = cfg.particles
        active = torch.ones(Q, dtype=torch.bool) if active is None else active
        active = active.to(self.states.device)
        predicted = self.clamp(self.states + cfg.velocity * (self.states - self.previous))
        # the layers weigh the particles in float32 (costs in px^2, a thousandth of a pixel's precision is plenty);
        # the polish and the estimate stay in float64
        layer_detections = detections.float()
        chunks = self._chunks(active, N)  # a held subject is not annealed
        keep = predicted[:, None].expand(Q, N, D).clone()
        w = predicted.new_full((Q, N), 1.0 / N)
        clouds = []  # each chunk's last layer's markers, for the spread
        for qs in chunks:
            chunk_gen = gen if isinstance(gen, torch.Generator) else [gen[i] for i in qs.tolist()]
            last, w[qs], pts = self._anneal(layer_detections[qs], predicted[qs, None].expand(-1, N, D), chunk_gen, qs)
            keep[qs] = last.to(keep)
            clouds.append(pts)
        estimate = (w[..., None] * keep).sum(1)  # (Q, D): the held subjects' predictions
        polished = None
        if cfg.polish_steps > 0:
            z = detections.double()
            cost = (ReprojectionCost(z, self.P, self.outlier_px) if cfg.polish == "reprojection" else
                    EpipolarCost(z, self.P, self.F, self.outlier_px, self.far_px))
            estimate, polished = self._polish(estimate, cost, active)  # (Q, D), and its markers (Q, M, 3)
        self.previous, self.states = self.states, torch.where(active[:, None], estimate, self.states)
        spreads = torch.full((Q,), math.nan, dtype=torch.float64)
        with torch.no_grad():
            for qs, pts in zip(chunks, clouds):
                at = (self.markers_all(self.states[qs, None].float(), qs) if polished is None else
                      polished[qs, ..., None].float())  # the estimate's markers (q, M, 3, 1)
                d2 = (pts - at).square().sum(2)  # (q, M, N)
                mask = self.marker_mask[qs]
                d2 = (d2 * mask[..., None]).sum(1) / mask.sum(1, keepdim=True)
                spreads[qs.cpu()] = (w[qs] * d2).sum(-1).sqrt().double().cpu()
        self.spreads = spreads
        return self.states.clone()
