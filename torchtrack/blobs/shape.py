"""The body's shape fitted to a frame's voxels: the union of the blobs' solid ellipsoids, analysis by synthesis.

The tracker's bone fit (:meth:`~torchtrack.tracking.markerless.MarkerlessTracker._fit_bone_lengths`) reads bone
lengths off blobs that EM fitted to the voxels; EM gives each voxel to one blob, and where ellipsoids overlap (the
pelvis over the thighs' tops, the head over the neck) the blobs it fits are not the drawn ones. Here the body's
ellipsoids themselves are moved to cover the voxels, with two symmetric terms, each a mean of a robust
(Cauchy) penalty ``rho(e) = tau^2 log(1 + e^2 / tau^2)`` of a distance in metres:

- every voxel, by its weight, at its centre's distance outside the union of ellipsoids less half its edge (a
  voxel the body's surface cuts is covered); the distance to an ellipsoid is taken along its ray from the
  ellipsoid's centre, ``|y| (1 - 1 / n)`` with ``y`` the point in the ellipsoid's frame and ``n`` its
  normalised radius (exact for a sphere, an upper bound otherwise);
- every ellipsoid, by its share of the body's volume, at fixed samples of its inside (the unit ball's mapped
  by its centre, axes and semi-axes) at their distance to the nearest voxel cube; samples out of the observed
  volume's sides and top count nothing (nothing is observed there).

The ellipsoids' centres and their semi-axes along their bones are affine in the fitted parameters ``x`` (at
fixed joint angles, a bone's length scales its blobs' offsets and every joint it carries: the caller gives the
columns), the rotations and cross semi-axes fixed. The samples' distances to the voxels are read off a distance
field of the voxels (:class:`VoxelDistance`), so that the objective is smooth in ``x`` (holding each sample's
nearest voxel for a round of L-BFGS, as in ICP, tied the samples to them and crept: a limb longer than the
model was fitted a little longer after each round, never reaching its length). Shapes: N voxels, K ellipsoids, P
parameters, M samples per ellipsoid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tqdm import tqdm

from torchtrack.checks import InputError, check_shape

__all__ = ["ShapeFrame", "ShapeModel", "VoxelDistance", "fit_shape", "fit_shape_frames", "outside_distance",
           "shape_energy", "unit_ball_samples"]


def unit_ball_samples(n: int, dtype: torch.dtype = torch.float64, device: torch.device | None = None,
                      seed: int = 0) -> torch.Tensor:
    """(n, 3) points uniform in the unit ball, the same for the same ``n`` and ``seed`` (rejection sampling)."""
    if n < 1:
        raise InputError(f"unit_ball_samples: n must be >= 1, got {n}")
    g = torch.Generator().manual_seed(seed)
    out, have = [], 0
    while have < n:
        u = torch.rand(2 * n + 8, 3, generator=g, dtype=torch.float64) * 2 - 1
        u = u[u.norm(dim=1) <= 1]
        out.append(u)
        have += u.shape[0]
    return torch.cat(out)[:n].to(dtype=dtype, device=device)


def outside_distance(points: torch.Tensor, centres: torch.Tensor, R_world: torch.Tensor, semi_axes: torch.Tensor
                     ) -> torch.Tensor:
    """(N, K) each point's distance outside each ellipsoid along the ray from the ellipsoid's centre (0 inside).

    Args:
        points: (N, 3); centres: (K, 3); R_world: (K, 3, 3), the ellipsoids' axes as columns; semi_axes: (K, 3).
    """
    y = torch.einsum("nkj,kji->nki", points[:, None, :] - centres[None], R_world)  # (N, K, 3) in each frame
    r = y.norm(dim=-1)  # (N, K)
    n = (y / semi_axes[None]).norm(dim=-1)  # (N, K) normalised radius, 1 on the surface
    return (r * (1 - 1 / n.clamp(min=1e-12))).clamp(min=0)


@dataclass(frozen=True)
class VoxelDistance:
    """The distance to a voxel set, sampled on a lattice and interpolated (trilinear, differentiable in the query
    points): each lattice node's distance to the nearest node inside a voxel (exact Euclidean distance
    transform) less one cell, so that the nodes beside the voxels' count as covered, as a voxel whose centre lies
    within half its edge of the body counts as covered (half a cell instead, the interpolated distance rises
    from the voxels' last nodes inwards of their faces, and a limb longer than the model was fitted shorter than
    with a whole cell); beyond the lattice, the distance to it is added.

    Attributes:
        field: (1, 1, Z, Y, X) distances (m). lower: (3,) the first node (x, y, z). cell: the lattice's spacing.
    """

    field: torch.Tensor
    lower: torch.Tensor
    cell: float

    @classmethod
    def of(cls, points: torch.Tensor, sizes: torch.Tensor, cell: float, margin: float = 0.5) -> VoxelDistance:
        """The field of the voxel cubes (centres ``points`` (N, 3), edges ``sizes`` (N,)) on a ``cell`` lattice
        over their box grown by ``margin`` (m)."""
        from scipy.ndimage import distance_transform_edt

        out = points  # the field's device and dtype; the lattice is built on the CPU (scipy's distance transform)
        points, sizes = points.detach().cpu(), sizes.detach().cpu()
        lo = (points - sizes[:, None] / 2).amin(0) - margin
        hi = (points + sizes[:, None] / 2).amax(0) + margin
        shape = torch.ceil((hi - lo) / cell).long() + 1  # (3,) nodes along x, y, z
        # the nodes inside each cube: its index range per axis
        first = torch.ceil((points - sizes[:, None] / 2 - lo) / cell - 1e-6).long()
        last = torch.floor((points + sizes[:, None] / 2 - lo) / cell + 1e-6).long()
        occupied = torch.zeros(tuple(shape.tolist()), dtype=torch.bool)
        n = (last - first + 1).clamp(min=1)
        for k in n.amax(1).unique().tolist():  # cubes of similar size together: a k^3 block of nodes each
            sel = n.amax(1) == k
            g = torch.arange(k)
            block = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)  # (k^3, 3)
            idx = first[sel][:, None, :] + block[None]  # (n, k^3, 3)
            inside = (idx <= last[sel][:, None, :]).all(-1)
            idx = torch.minimum(idx[inside].clamp(min=0), shape - 1)
            occupied[idx[:, 0], idx[:, 1], idx[:, 2]] = True
        near = torch.round((points - lo) / cell).long()  # and each cube's nearest node (cubes under a cell
        occupied[near[:, 0], near[:, 1], near[:, 2]] = True  # may hold none)
        dist = torch.from_numpy(distance_transform_edt(~occupied.numpy())) * cell - cell
        field = dist.clamp(min=0).permute(2, 1, 0)[None, None].to(out)  # (1, 1, Z, Y, X) for grid_sample
        return cls(field, lo.to(out), cell)

    def __call__(self, query: torch.Tensor) -> torch.Tensor:
        """(Q, 3) points -> (Q,) their distances to the voxels (m)."""
        size = torch.tensor(self.field.shape[:1:-1], dtype=query.dtype, device=query.device)  # (3,) x, y, z nodes
        upper = self.lower + (size - 1) * self.cell
        inside = torch.maximum(torch.minimum(query, upper), self.lower)
        grid = (2 * (inside - self.lower) / (upper - self.lower) - 1).reshape(1, 1, 1, -1, 3)
        d = torch.nn.functional.grid_sample(self.field, grid, mode="bilinear", align_corners=True)
        return d.reshape(-1) + (query - inside).norm(dim=-1)


@dataclass(frozen=True)
class ShapeModel:
    """K ellipsoids affine in P parameters: centres ``centres + d_centres @ x``, semi-axes along their first
    axis ``semi_axes[:, 0] + d_along @ x`` (at least ``MIN_SEMI_M``), the rest fixed.

    Attributes:
        centres: (K, 3). R_world: (K, 3, 3) axes as columns (the first along the bone). semi_axes: (K, 3).
        d_centres: (K, 3, P). d_along: (K, P).
    """

    centres: torch.Tensor
    R_world: torch.Tensor
    semi_axes: torch.Tensor
    d_centres: torch.Tensor
    d_along: torch.Tensor

    MIN_SEMI_M = 0.01

    def __post_init__(self) -> None:
        check_shape(self.centres, ("K", 3), "centres")
        K = self.centres.shape[0]
        check_shape(self.R_world, (K, 3, 3), "R_world")
        check_shape(self.semi_axes, (K, 3), "semi_axes")
        check_shape(self.d_centres, (K, 3, "P"), "d_centres")
        check_shape(self.d_along, (K, self.d_centres.shape[2]), "d_along")

    @property
    def num_params(self) -> int:
        return int(self.d_along.shape[1])

    def at(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(P,) parameters -> centres (K, 3), semi-axes (K, 3)."""
        centres = self.centres + self.d_centres @ x
        along = (self.semi_axes[:, :1] + (self.d_along @ x)[:, None]).clamp(min=self.MIN_SEMI_M)
        return centres, torch.cat([along, self.semi_axes[:, 1:]], 1)


def _samples(model: ShapeModel, x: torch.Tensor, unit: torch.Tensor) -> torch.Tensor:
    """(K, M, 3) the unit ball's samples ``unit`` (M, 3) inside each ellipsoid at ``x``."""
    centres, semi = model.at(x)
    return centres[:, None, :] + torch.einsum("kij,kmj->kmi", model.R_world, semi[:, None, :] * unit[None])


def shape_energy(model: ShapeModel, x: torch.Tensor, points: torch.Tensor, sizes: torch.Tensor,
                 weights: torch.Tensor, unit: torch.Tensor, distance: VoxelDistance, tau: float = 0.05,
                 volume_m: tuple[Sequence[float], Sequence[float]] | None = None) -> torch.Tensor:
    """The union's misfit to the voxels at ``x`` (m^2, the two terms of the module's docstring summed).

    Args:
        model: the ellipsoids (K). x: (P,). points: (N, 3) voxel centres; sizes: (N,) edges; weights: (N,)
        summing to 1. unit: (M, 3) unit-ball samples. distance: the voxels' :class:`VoxelDistance`.
        tau: the robust penalty's scale (m). volume_m: the observed box (lower, upper) or None.
    """
    centres, semi = model.at(x)
    outside = outside_distance(points, centres, model.R_world, semi).min(1).values  # (N,)
    e_vox = (outside - sizes / 2).clamp(min=0)
    q = _samples(model, x, unit).reshape(-1, 3)  # (K * M, 3)
    d = distance(q).reshape(semi.shape[0], -1)  # (K, M)
    seen = torch.ones_like(d)
    if volume_m is not None:
        lower, upper = (q.new_tensor(list(v)) for v in volume_m)
        seen = ((q[:, :2] >= lower[:2]).all(-1) & (q <= upper).all(-1)).reshape(d.shape).to(d)
    vol = semi.detach().prod(-1)  # (K,) proportional to the volumes
    share = vol / vol.sum()

    def rho(e: torch.Tensor) -> torch.Tensor:
        return tau ** 2 * torch.log1p((e / tau) ** 2)

    return (weights * rho(e_vox)).sum() + (share[:, None] * seen * rho(d)).mean(1).sum()


def fit_shape(model: ShapeModel, points: torch.Tensor, sizes: torch.Tensor, weights: torch.Tensor,
              ridge: torch.Tensor, target: torch.Tensor, starts: Sequence[torch.Tensor] = (),
              volume_m: tuple[Sequence[float], Sequence[float]] | None = None, samples: int = 96,
              tau: float = 0.05, rounds: int = 4, iterations: int = 60, cell: float = 0.015
              ) -> tuple[torch.Tensor, float]:
    """Parameters ``x`` (P,) of least :func:`shape_energy` plus ``sum(ridge * (x - target)^2)``: one frame's
    :func:`fit_shape_frames` with every parameter its own.

    Each start (default: only zeros) is refined by ``rounds`` of L-BFGS (``iterations`` each); the start whose
    result has the least objective wins (the union's energy has local minima along what the voxels hardly tell
    apart, e.g. the neck's height against the head's length). The objective is divided by ``tau^2`` for L-BFGS,
    whose tolerances expect one of order one (in m^2 it stopped at once). ``cell``: the voxels' distance field's
    spacing (m).

    Args:
        model: K ellipsoids in P parameters. points: (N, 3); sizes: (N,); weights: (N,) >= 0, not all 0.
        ridge: (P,) >= 0; target: (P,). starts: (P,) tensors. volume_m: the observed box or None.

    Returns:
        x (P,) and its objective (m^2).
    """
    x, _, energy = fit_shape_frames([ShapeFrame(model, points, sizes, weights, volume_m)], ridge, target, starts,
                                    local=0, samples=samples, tau=tau, rounds=rounds, iterations=iterations,
                                    cell=cell)
    return x, energy


@dataclass(frozen=True)
class ShapeFrame:
    """One frame of :func:`fit_shape_frames`: its ellipsoids (at the frame's pose) and its voxels.

    Attributes:
        model: K ellipsoids in P parameters. points: (N, 3) voxel centres; sizes: (N,) edges; weights: (N,) >= 0,
        not all 0. volume_m: the observed box (lower, upper) or None.
    """

    model: ShapeModel
    points: torch.Tensor
    sizes: torch.Tensor
    weights: torch.Tensor
    volume_m: tuple[Sequence[float], Sequence[float]] | None = None


def fit_shape_frames(frames: Sequence[ShapeFrame], ridge: torch.Tensor, target: torch.Tensor,
                     starts: Sequence[torch.Tensor] = (), local: int = 0, samples: int = 96, tau: float = 0.05,
                     rounds: int = 4, iterations: int = 60, cell: float = 0.015, progress: str | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, float]:
    """One body fitted to several frames' voxels at once: the parameters shared by every frame (each model's
    first ``S = P - local``, e.g. the bones' scales) and ``local`` more per frame (each model's last, e.g. a root
    shift that the frame's pose error leaves to it) of least mean :func:`shape_energy` over the frames plus
    ``sum(ridge * (shared - target)^2)``. A pose that bends a joint shows where it is, which a union of ellipsoids
    in one straight pose hides (the hip's height under the pelvis against the legs' length).

    Each start (of the shared parameters; default only zeros; the local ones start at 0) is refined by ``rounds``
    of L-BFGS (``iterations`` each), the least objective winning; see :func:`fit_shape`.

    Args:
        frames: F >= 1 frames whose models have the same P. ridge: (S,) >= 0; target: (S,). starts: (S,) tensors.
        progress: the label of a progress bar over the starts' rounds (None: no bar).

    Returns:
        the shared parameters (S,), the local ones (F, local), and the objective (m^2).
    """
    if not frames:
        raise InputError("fit_shape_frames: no frames")
    P = frames[0].model.num_params
    if not 0 <= local <= P:
        raise InputError(f"fit_shape_frames: local must be in [0, {P}] (the models' parameters), got {local}")
    S, F = P - local, len(frames)
    check_shape(ridge, (S,), "ridge")
    check_shape(target, (S,), "target")
    dt = frames[0].model.centres.dtype
    device = frames[0].points.device
    unit = unit_ball_samples(samples, dt, device)
    prepared = []
    for f, fr in enumerate(frames):
        if fr.model.num_params != P:
            raise InputError(f"fit_shape_frames: frame {f}'s model has {fr.model.num_params} parameters, frame 0's "
                             f"{P}")
        check_shape(fr.points, ("N", 3), f"frames[{f}].points")
        N = fr.points.shape[0]
        check_shape(fr.sizes, (N,), f"frames[{f}].sizes")
        check_shape(fr.weights, (N,), f"frames[{f}].weights")
        total = float(fr.weights.sum())
        if N == 0 or not total > 0 or not math.isfinite(total):
            raise InputError(f"fit_shape: the voxels' weights must be finite with a positive sum, got {total} over "
                             f"{N} (frame {f})")
        points, sizes = fr.points.to(dt), fr.sizes.to(dt)
        prepared.append((fr.model, points, sizes, (fr.weights / total).to(dt), VoxelDistance.of(points, sizes, cell),
                         fr.volume_m))
    ridge, target = ridge.to(dt), target.to(dt)

    def objective(x: torch.Tensor) -> torch.Tensor:
        shared, own = x[:S], x[S:].reshape(F, local)
        energy = sum(shape_energy(model, torch.cat([shared, own[f]]), points, sizes, weights, unit, distance, tau,
                                  volume_m)
                     for f, (model, points, sizes, weights, distance, volume_m) in enumerate(prepared))
        return energy / F + (ridge * (shared - target) ** 2).sum()

    best: tuple[float, torch.Tensor] | None = None
    starts = list(starts) or [torch.zeros(S, dtype=dt, device=device)]
    bar = tqdm(total=len(starts) * rounds, desc=progress, unit="round", disable=progress is None, leave=False)
    for x0 in starts:
        check_shape(x0, (S,), "start")
        x = torch.cat([x0.detach().to(dt), x0.new_zeros(F * local, dtype=dt)]).requires_grad_(True)
        opt = torch.optim.LBFGS([x], lr=1, max_iter=iterations, line_search_fn="strong_wolfe")

        def closure() -> torch.Tensor:
            opt.zero_grad()
            e = objective(x) / tau ** 2
            e.backward()
            return e
        with torch.enable_grad():
            for _ in range(rounds):
                opt.step(closure)
                bar.update(1)
        with torch.no_grad():
            e = float(objective(x))
        if best is None or e < best[0]:
            best = (e, x.detach())
    bar.close()
    x = best[1]
    return x[:S], x[S:].reshape(F, local), best[0]
