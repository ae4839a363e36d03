"""Real-time hierarchical visual hull with colour (Caillette & Howard 2004, §3.2-3.3; ALGORITHMS.md §2).

Conventions (world Z up, metres; OpenCV cameras, pixel centres at integer coordinates):

* Grids. Level 0: cubic voxels of edge ``e0`` from ``lower_m`` (upper side rounded up to whole voxels, as
  ``GridSpec``); level ``l``: edge ``e0 / 2**l``, voxel ``ijk`` has centre ``lower + (ijk + 0.5) e_l`` and children
  ``2 ijk + {0, 1}^3``. The finest edge is exactly ``finest_voxel_m`` after
  ``L = round(log2(extent / (start_resolution * finest_voxel_m)))`` subdivisions (2 m at 1.5 cm: 17 x 17 x 18
  voxels of 12 cm, then 6, 3, 1.5 cm, a 136^3 finest grid).
* Sample pattern: a voxel of edge ``e`` is read at the 8 points ``centre + (+-e/4)^3`` (its children's centres),
  each at its nearest pixel. A view *sees* a voxel when all 8 samples fall inside its image, in front of it, with
  finite values (NaN pixels, e.g. a dead camera frame, count as unseen). Level 0 is projected exactly (the plan,
  :class:`~torchtrack.occupancy.hull_plan.HullPlan`, built once per rig and zone). Below, the paper's pre-computed
  pattern: per level-0 voxel and camera, a quadratic fitted to the exact (distorted) projections of
  ``centre + {-3/8 e0, 0, 3/8 e0}^3`` is re-centred on each parent and its cross terms dropped, so a parent's 64
  child samples are ``uv_p + f_x(dx) + f_y(dy) + f_z(dz)`` (per-axis quadratics). Error against the exact projection: mean 0.02 px, max 0.11 px at level 1 (12 cm voxels, 3.5 m
  away), 4x less per level below; the nearest pixel changes only within that distance of a pixel border.
* Sample values: squared Mahalanobis distances to the background (YUV, 3 channels; the background model's
  per-pixel foreground test is ``d2 > FOREGROUND_MAHALANOBIS2 = 16``), clipped at ``clip_mahalanobis2``; per view
  the mean ``m`` and the population variance ``s`` of the 8 samples.
* Classification (all views at once, then reduced; the same result as the paper's view-by-view order with its
  early out): background if some seeing view has ``m < t_low`` or fewer than ``min_views`` views see the voxel;
  else edge if some seeing view has ``s > t_var``; else foreground if every seeing view has ``m > t_high``; else
  unknown. Above the finest level, a voxel called background by ``m < t_low`` is an edge instead when in every
  seeing view a foreground pixel lies within a child's projected width of one of its samples
  (``footprint_early_out``: the samples read a max-filtered foreground mask): its samples missed a thin part that
  its children hold. Edges are split into their 8 children; at the finest level an edge is kept iff every seeing
  view has ``m >= t_finest_edge``, ``m`` there taken over 9 samples, the 8 and the voxel centre (``centre_sample``;
  with the default threshold, half the clip, a voxel on the silhouette's border whose samples split 4 : 4 is kept
  iff its centre is on the silhouette; not when the zone has a single level).
  Unknowns take the majority of their 26 same-level neighbours that are decided (foreground: kept at this or a
  coarser level; background: discarded); a tie goes to foreground (carving needs evidence). Kept voxels stay at
  their level: big inside, small at the surface (EM weighs them by size^3).
* Colours: per kept voxel and view, the mean colour of its samples with ``d2 >= t_low`` (all 8 when none is),
  NaN where the view does not see it, in the colour space of the ``colour`` input (:func:`hull_from_images`: the
  background model's gain-normalised YUV).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchtrack.checks import InputError, check_shape
from torchtrack.occupancy.hull_plan import HullPlan

__all__ = ["HierarchicalHull", "HullConfig", "SparseVoxels", "hierarchical_hull", "hull_from_images"]

#: Largest number of samples (cameras x voxels x 8) evaluated at once; bigger levels are processed in chunks.
_CHUNK_SAMPLES = 1 << 22


@dataclass(frozen=True)
class HullConfig:
    """Zone, resolution and thresholds of :func:`hierarchical_hull`.

    Thresholds are in units of the background's squared Mahalanobis distance (3 colour channels: a background
    pixel has d2 ~ chi-square(3), mean 3; the background model calls a pixel foreground above 16).

    Attributes:
        lower_m, upper_m: corners of the zone of interest (world, m); None: the caller fills them in.
        start_resolution: about this many voxels along the longest axis at level 0.
        finest_voxel_m: edge of the finest voxels (m); subdivision stops there.
        clip_mahalanobis2: samples are clipped here (64 = 4 x 16): a sample this far from the background is
            certainly foreground, and the variance then measures the mix of foreground and background samples,
            not the texture of the foreground.
        t_low: mean below it in a view -> background. 7: pure background gives about 3 (the chi-square(3)
            mean; 8 independent samples exceed 7 with probability ~2e-4), one clipped foreground sample among 8
            gives >= 64 / 8 = 8, so a voxel touched by foreground in every view is not carved.
        t_high: mean above it in every seeing view -> foreground. 18: just above the per-pixel foreground
            threshold (16), i.e. the samples are foreground on average.
        t_var: variance above it in a view -> edge. 200: a mix of 1 clipped foreground and 7 background samples
            has ~400-450, 4 + 4 ~900; background noise stays near 6 (chi-square(3) variance), a foreground part
            whose samples all exceed 16 has at most (64 - 16)^2 / 4 = 576 (then it is just subdivided).
        t_finest_edge: an edge voxel at the finest level is kept when its mean reaches this in every seeing view
            (32 = half of the clip: about half of its samples are foreground, the voxel centre is about on the
            silhouette).
        centre_sample: the finest edge rule averages a 9th sample, at the voxel centre, with the 8. The 8 samples
            of a voxel on the silhouette's border split 4 : 4 (mean ~32 = t_finest_edge) whether its centre lies
            just inside or just outside; the centre's pixel breaks the tie. False: ties are kept, a half-voxel
            shell around the body that lowers the IoU with it (``scripts/eval_occupancy.py --hull
            centre_sample=false``; docs/results.md, "Occupancy").
        min_views: fewer views seeing a voxel -> discarded. None: min(2, number of cameras).
        footprint_early_out: above the finest level, a voxel that ``t_low`` calls background is subdivided
            (an edge) instead when, in every seeing view, the window of a child's projected width around one of
            its 8 samples holds a foreground pixel (``d2 > footprint_mahalanobis2``): its samples missed a thin
            part (a forearm between samples 6 cm apart) that its children hold. False: the paper's 8 point
            samples only (the hull then loses forearms and hands at the 12 and 6 cm levels).
        footprint_mahalanobis2: foreground pixels for ``footprint_early_out``; 16 is the background model's
            per-pixel foreground test (background noise exceeds it at 0.1 % of the pixels).
    """

    lower_m: tuple[float, float, float] | None = None
    upper_m: tuple[float, float, float] | None = None
    start_resolution: int = 16
    finest_voxel_m: float = 0.015
    clip_mahalanobis2: float = 64.0
    t_low: float = 7.0
    t_high: float = 18.0
    t_var: float = 200.0
    t_finest_edge: float = 32.0
    min_views: int | None = None
    footprint_early_out: bool = True
    centre_sample: bool = True
    footprint_mahalanobis2: float = 16.0

    def __post_init__(self) -> None:
        if (self.lower_m is None) != (self.upper_m is None):
            raise InputError("HullConfig: give both lower_m and upper_m, or neither")
        if self.lower_m is not None:
            lo, up = tuple(float(v) for v in self.lower_m), tuple(float(v) for v in self.upper_m)  # lists from YAML
            object.__setattr__(self, "lower_m", lo)
            object.__setattr__(self, "upper_m", up)
            if len(lo) != 3 or len(up) != 3 or not all(math.isfinite(x) and y > x for x, y in zip(lo, up)):
                raise InputError(f"HullConfig: need 3 finite values with upper_m > lower_m, got {lo}, {up}")
        checks = {"start_resolution >= 1": self.start_resolution >= 1, "finest_voxel_m > 0": self.finest_voxel_m > 0,
                  "0 <= t_low < t_high < clip_mahalanobis2": 0 <= self.t_low < self.t_high < self.clip_mahalanobis2,
                  "t_var > 0": self.t_var > 0, "min_views >= 1": self.min_views is None or self.min_views >= 1,
                  "t_low <= t_finest_edge <= clip_mahalanobis2":
                      self.t_low <= self.t_finest_edge <= self.clip_mahalanobis2,
                  "footprint_mahalanobis2 >= 0": self.footprint_mahalanobis2 >= 0}
        failed = [rule for rule, ok in checks.items() if not ok]
        if failed:
            raise InputError(f"HullConfig: need {', '.join(failed)}; got {self}")

    def level0(self) -> tuple[int, float, list[int]]:
        """The hierarchy's start: the number of levels below it, its cubes' edge (m) and how many of them lie
        along each axis (the zone rounded up to whole cubes)."""
        if self.lower_m is None:
            raise InputError("HullConfig.lower_m / upper_m (the zone of interest) must be set")
        lo, up = self.lower_m, self.upper_m
        extent = max(u - l for l, u in zip(lo, up))
        levels = max(0, round(math.log2(extent / (self.start_resolution * self.finest_voxel_m))))
        e0 = self.finest_voxel_m * 2 ** levels
        return levels, e0, [max(1, math.ceil((u - l) / e0 - 1e-9)) for l, u in zip(lo, up)]

    def covered_box(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """The box the hull's cubes cover: the zone's lower corner, its upper one rounded up to whole level-0
        cubes (voxels are found up to there)."""
        _, e0, n0 = self.level0()
        return self.lower_m, tuple(lo + n * e0 for lo, n in zip(self.lower_m, n0))  # type: ignore[return-value]


@dataclass
class SparseVoxels:
    """Kept voxels of several sizes (N voxels, C cameras).

    Attributes:
        centres: (N, 3) world centres (m). sizes: (N,) edge lengths (m). level: (N,) int64 (0 = coarsest).
        colours: (N, C, 3) mean sample colour per view (colour space of the input), NaN where unseen.
        grid_lower_m, finest_voxel_m, finest_shape: the finest grid the voxels are aligned to (defaults of
            :meth:`to_dense`).
    """

    centres: Tensor
    sizes: Tensor
    colours: Tensor
    level: Tensor
    grid_lower_m: tuple[float, float, float] | None = None
    finest_voxel_m: float | None = None
    finest_shape: tuple[int, int, int] | None = None

    @property
    def num_voxels(self) -> int:
        return int(self.centres.shape[0])

    def volume_m3(self) -> float:
        """Total volume of the kept voxels."""
        return float((self.sizes.double() ** 3).sum())

    def to_dense(self, lower: tuple[float, float, float] | Tensor | None = None, voxel_size: float | None = None,
                 shape: tuple[int, int, int] | None = None) -> Tensor:
        """Boolean occupancy of a regular grid: cell ``ijk`` (centre ``lower + (ijk + 0.5) voxel_size``) is True
        when its centre lies in a kept voxel (half-open cube ``[c - s/2, c + s/2)``).

        Args:
            lower, voxel_size, shape: the grid; None: the finest grid of the hull.

        Returns:
            (nx, ny, nz) bool; flattened, cell ``(i * ny + j) * nz + k`` (as ``GridSpec``).
        """
        lower = self.grid_lower_m if lower is None else lower
        voxel_size = self.finest_voxel_m if voxel_size is None else voxel_size
        shape = self.finest_shape if shape is None else shape
        if lower is None or voxel_size is None or shape is None:
            raise InputError("to_dense: give lower, voxel_size and shape (this SparseVoxels has no grid)")
        dev = self.centres.device
        out = torch.zeros(tuple(int(n) for n in shape), dtype=torch.bool, device=dev)
        lo_m, dims = torch.as_tensor(lower, dtype=torch.float64, device=dev), torch.tensor(out.shape, device=dev)
        half = self.sizes.double()[:, None] / 2  # (N, 1)
        first = torch.ceil((self.centres.double() - half - lo_m) / voxel_size - 0.5).long()  # (N, 3)
        end = torch.ceil((self.centres.double() + half - lo_m) / voxel_size - 0.5).long()  # (N, 3), exclusive
        span = (end - first).amax(1) if self.num_voxels else end[:, 0]
        for n in torch.unique(span).tolist():  # per cube size in cells
            r = torch.arange(max(n, 0), device=dev)
            cells = first[span == n][:, None] + torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
            c = cells[((cells < end[span == n][:, None]) & (cells >= 0) & (cells < dims)).all(-1)]  # (M, 3)
            out[c[:, 0], c[:, 1], c[:, 2]] = True
        return out


def _max_filter(x: Tensor, width: int, dim: int) -> Tensor:
    """Centred running maximum of odd ``width`` along ``dim`` (outside the tensor counts as the lowest value of
    the dtype; NaN spreads),
    by doubling: ``log2(width) + 1`` element-wise maxima instead of ``width`` (many times faster on a CPU than
    ``F.max_pool2d`` with stride 1, whose cost grows with the width)."""
    r = width // 2
    pad = [0, 0] * (x.dim() - 1 - dim) + [r, r]
    low = float("-inf") if x.is_floating_point() else torch.iinfo(x.dtype).min
    y = F.pad(x, pad, value=low)  # length n + 2r along dim
    w = 1
    while 2 * w <= width:  # y[i] = max of the w values from i
        y = torch.maximum(y.narrow(dim, 0, y.shape[dim] - w), y.narrow(dim, w, y.shape[dim] - w))
        w *= 2
    if w < width:  # two overlapping windows of w cover width (w > width / 2)
        k = width - w
        y = torch.maximum(y.narrow(dim, 0, y.shape[dim] - k), y.narrow(dim, k, y.shape[dim] - k))
    return y


# -------------------------------------------------------------------------------------- sampling a level

_BG, _UNKNOWN, _FG, _EDGE = -1, 0, 1, 2


def _children_samples(plan: HullPlan, level: int, parents: Tensor, dtype: torch.dtype,
                      centres: bool = False) -> tuple[Tensor, ...]:
    """Sample pixels of the 8 children of every parent, from the quadratic of the parent's level-0 ancestor
    re-centred on the parent (exact for a quadratic) without its cross terms.

    Args:
        level: the children's level (>= 1). parents: (P, 3) int64 at ``level - 1``. dtype: of the pixel arithmetic.

    Returns:
        ijk (8P, 3) int64 children (voxel ``g P + p`` is child g of parent p), idx (C, 8, 8P) int32 flat sample
        indices (row-offset layout, clamped into the maps; meaningful where seen), sees (C, 8P) bool; with
        ``centres``, also idx_centre (C, 8P) int32: each child centre's pixel (the mean of its samples' offsets).
    """
    C, P, n0 = plan.C, parents.shape[0], plan.n0
    e_p, b = plan.edge(level - 1), 2 ** (level - 1)
    anc = torch.div(parents, b, rounding_mode="floor")  # (P, 3) level-0 ancestors
    a = (anc[:, 0] * n0[1] + anc[:, 1]) * n0[2] + anc[:, 2]  # (P,)
    delta = ((parents - anc * b + 0.5) * e_p - 0.5 * plan.e0).T.to(dtype)  # (3, P) parent centre - ancestor's
    model = plan.as_("model", dtype).index_select(0, a).T.reshape(C, 2, 13, P).contiguous()  # (C, 2, 13, P)
    h_delta = (model[:, :, 4:].reshape(C, 2, 3, 3, P) * delta).sum(3)  # (C, 2, 3, P) Hessian @ delta
    grad = model[:, :, 1:4] + h_delta  # (C, 2, 3, P) at the parent centre
    uv0 = model[:, :, 0] + ((model[:, :, 1:4] + 0.5 * h_delta) * delta).sum(2)  # (C, 2, P)
    tau = plan.as_("tau", dtype) * e_p  # (4, 1)
    curv = 0.5 * model[:, :, (4, 8, 12)]  # (C, 2, 3, P) half the Hessian's diagonal
    f = grad[:, :, :, None] * tau + curv[:, :, :, None] * (tau * tau)  # (C, uv, axis, 4, P) pixel offsets
    f = f.reshape(C, 2, 3, 2, 2, P)  # (C, uv, axis, sample, child half, P)
    # A child is seen when the bounding box of its 8 samples lies inside the image.
    lo = uv0[:, :, None] + _axis_sum(f.amin(3))  # (C, uv, 8, P)
    hi = uv0[:, :, None] + _axis_sum(f.amax(3))
    sees = ((lo >= -0.5) & (hi < plan.size_wh - 0.5)).all(1) & plan.model_ok[:, a][:, None]  # (C, 8, P)
    base = uv0 + plan.as_("shift", dtype)  # (C, 2, P): +0.5 so that truncation rounds; camera c's rows offset by c H
    pix, mid = [], []
    for k in range(2):  # u, v: (C, sx, sy, sz, cx, cy, cz, P)
        fk = f[:, k]  # (C, axis, sample, child, P)
        p = (base[:, k].reshape(C, 1, 1, 1, 1, 1, 1, P) + fk[:, 0].reshape(C, 2, 1, 1, 2, 1, 1, P)
             + fk[:, 1].reshape(C, 1, 2, 1, 1, 2, 1, P)) + fk[:, 2].reshape(C, 1, 1, 2, 1, 1, 2, P)
        pix.append(p.to(torch.int32))
        if centres:  # (C, cx, cy, cz, P)
            fm = fk.mean(2)  # (C, axis, child, P)
            mid.append((base[:, k].reshape(C, 1, 1, 1, P) + fm[:, 0].reshape(C, 2, 1, 1, P)
                        + fm[:, 1].reshape(C, 1, 2, 1, P) + fm[:, 2].reshape(C, 1, 1, 2, P)).to(torch.int32))
    last = C * plan.H * plan.W - 1
    idx = pix[1].mul_(plan.W).add_(pix[0]).clamp_(0, last)
    ijk = (plan.child + parents * 2).reshape(-1, 3)
    out = (ijk, idx.reshape(C, 8, 8 * P), sees.reshape(C, 8 * P))
    if centres:
        out += (mid[1].mul_(plan.W).add_(mid[0]).clamp_(0, last).reshape(C, 8 * P),)
    return out


def _axis_sum(g: Tensor) -> Tensor:
    """(C, uv, 3, 2, P) per-axis values of each child half -> (C, uv, 8, P) their sum per child (cx, cy, cz)."""
    C, _, _, _, P = g.shape
    out = (g[:, :, 0].reshape(C, 2, 2, 1, 1, P) + g[:, :, 1].reshape(C, 2, 1, 2, 1, P)
           + g[:, :, 2].reshape(C, 2, 1, 1, 2, P))
    return out.reshape(C, 2, 8, P)


# -------------------------------------------------------------------------------------- classification


def _classify(m: Tensor, s: Tensor, sees: Tensor, config: HullConfig, min_views: int, finest: bool,
              near_fg: Tensor | None = None, m_edge: Tensor | None = None) -> Tensor:
    """Per voxel label (V,) int8 (-1 background, 0 unknown, 1 foreground, 2 edge) from the per-view mean ``m``,
    variance ``s`` and ``sees``, all (C, V); at the finest level edges become foreground or background. The
    rules read the seeing views only: the smallest mean decides background / foreground, the largest variance
    edges. ``near_fg`` (C, V) bool, above the finest level: a foreground pixel lies in the footprint of one of
    the voxel's samples; a voxel that ``m`` calls background but that has one in every seeing view is an edge.
    ``m_edge`` (C, V), at the finest level: the mean that decides edges there (default ``m``)."""
    unseen = ~sees
    m_min = m.masked_fill(unseen, float("inf")).amin(0)  # (V,) the most background-like seeing view
    edge = s.masked_fill(unseen, 0.0).amax(0) > config.t_var  # (V,)
    label = (m_min > config.t_high).to(torch.int8)  # foreground or unknown
    background = m_min < config.t_low
    if finest:
        m_keep = m_min if m_edge is None else m_edge.masked_fill(unseen, float("inf")).amin(0)
        label.masked_fill_(edge, _FG).masked_fill_(edge & (m_keep < config.t_finest_edge), _BG)
    else:
        label.masked_fill_(edge, _EDGE)
        if near_fg is not None:  # the samples missed what the children hold: look closer
            look = background & (near_fg | unseen).all(0)
            label.masked_fill_(look, _EDGE)
            background &= ~look
    return label.masked_fill_(background | (sees.sum(0) < min_views), _BG)


def _resolve_unknown(plan: HullPlan, level: int, ijk: Tensor, label: Tensor,
                     kept: list[tuple[int, Tensor, object]]) -> Tensor:
    """Unknown voxels (label 0) take the majority of their 26 decided same-level neighbours; tie -> foreground.

    A neighbour votes foreground when it is a foreground candidate or lies in a kept coarser voxel, background
    when it is a background candidate or neither (discarded earlier), nothing when it is an edge or unknown
    candidate or outside the zone. The votes are read from a dense int8 map of this level over the box of the
    candidates and the kept voxels, one cell wider: 0 outside the zone, background inside, then the kept coarser
    voxels painted foreground and the candidates' labels written (edges as 0; candidates and kept voxels never
    overlap). Cells are linear keys in the box, so a neighbour is a key offset.

    Args:
        ijk: (V, 3) candidates of ``level``; label: (V,) int8 as :func:`_classify`.
        kept: (level, ijk, ...) of the kept voxels of coarser levels.

    Returns:
        (V,) int8 labels without unknowns.
    """
    unknown = (label == _UNKNOWN).nonzero()[:, 0]
    if unknown.numel() == 0:
        return label
    kept = [(2 ** (level - k), x) for k, x, _ in kept if x.numel()]  # (cells per axis, ijk)
    lo = torch.stack([ijk.amin(0)] + [x.amin(0) * s for s, x in kept]).amin(0) - 1
    hi = torch.stack([ijk.amax(0) + 1] + [(x.amax(0) + 1) * s for s, x in kept]).amax(0) + 1  # exclusive
    (l0, l1, l2), (d0, d1, d2) = lo.tolist(), (hi - lo).tolist()
    stride = torch.tensor([d1 * d2, d2, 1], device=ijk.device)
    votes = torch.zeros(d0 * d1 * d2, dtype=torch.int8, device=label.device)  # outside the zone: no vote
    n = [k * 2 ** level for k in plan.n0]
    votes.view(d0, d1, d2)[max(0, -l0):n[0] - l0, max(0, -l1):n[1] - l1, max(0, -l2):n[2] - l2] = _BG
    for s, x in kept:  # a kept voxel of level k covers s^3 cells here, s = 2^(level - k)
        r = torch.arange(s, device=ijk.device)
        block = (torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1) * stride).sum(-1).reshape(-1)  # (s^3,)
        votes[(((x * s - lo) * stride).sum(-1)[:, None] + block).reshape(-1)] = _FG
    key = ((ijk - lo) * stride).sum(-1)  # (V,)
    votes[key] = label.masked_fill(label == _EDGE, _UNKNOWN)
    vote = votes[key[unknown][:, None] + (plan.neighbours * stride).sum(-1)]  # (U, 26)
    label = label.clone()
    label[unknown] = (vote.sum(-1, dtype=torch.int32) >= 0).to(torch.int8) * 2 - 1  # tie -> foreground
    return label


def _take(x: Tensor, at: Tensor) -> Tensor:
    """(C, 8, V) -> (C, 8, len(at)) voxels ``at`` (``gather`` with an expanded index: several times faster on
    the CPU than ``index_select`` along the last axis)."""
    return x.gather(2, at.expand(*x.shape[:2], -1))


def _colours(colour: Tensor, idx: Tensor, d: Tensor, sees: Tensor, t_low: float, pixel0: Tensor) -> Tensor:
    """Mean colour of the samples, (K, C, 3): over the samples with ``d >= t_low`` (all 8 when none is), NaN where
    unseen. colour: (C, 3, H, W); idx: (C, 8, K) row-offset sample indices ``c H W + pixel``; d: (C, 8, K)
    clipped distances; sees: (C, K); pixel0: (C, 1, 1) ``c H W``."""
    C, _, K = idx.shape
    HW = colour.shape[2] * colour.shape[3]
    w = d >= t_low
    w = (w | ~w.any(1, keepdim=True)).to(colour.dtype)  # (C, 8, K)
    pixel = idx.long() - pixel0  # (C, 8, K) within the camera
    pixel.clamp_(0, HW - 1)  # unseen views (NaN below) may point anywhere
    col = colour.reshape(C, 3, HW).gather(2, pixel.reshape(C, 1, 8 * K).expand(C, 3, 8 * K)).reshape(C, 3, 8, K)
    mean = (col * w[:, None]).sum(2) / w.sum(1)[:, None]  # (C, 3, K)
    return mean.masked_fill_(~sees[:, None], float("nan")).permute(2, 0, 1)


# ------------------------------------------------------------------------------------------- the hull


class HierarchicalHull(nn.Module):
    """The hierarchical visual hull of one rig and zone, frame by frame (see the module docstring).

    The plan (:class:`~torchtrack.occupancy.hull_plan.HullPlan`: level 0 projected exactly, the projection model
    of the levels below) is built once here from the rig as it is now, and held as buffers: ``.to(device)`` moves
    it; a rig changed later needs a new module.

    Args:
        rig: ``CameraRig`` of C cameras, all of image size W x H. config: zone (required), resolution, thresholds.

    Raises:
        InputError: no zone, mixed image sizes, min_views > C.
    """

    def __init__(self, rig: nn.Module, config: HullConfig) -> None:
        super().__init__()
        self.config = config
        self.plan = HullPlan(rig, config)
        self.min_views = min(2, self.plan.C) if config.min_views is None else config.min_views
        if self.min_views > self.plan.C:
            raise InputError(f"HullConfig.min_views = {self.min_views} exceeds the {self.plan.C} cameras")

    def forward(self, mahal2: Tensor, colour: Tensor) -> SparseVoxels:
        """One frame's hull.

        Args:
            mahal2: (C, H, W) squared Mahalanobis distance of every pixel to its background (NaN: no data).
            colour: (C, 3, H, W) colour image stored per voxel (any colour space; YUV in :meth:`from_images`).

        Returns:
            :class:`SparseVoxels` of the kept voxels (possibly none), centres and sizes in ``mahal2.dtype``.

        Raises:
            ShapeError: shapes do not fit the rig. InputError: not floating point or not on the plan's device.
        """
        return _hull(self.plan, self.config, self.min_views, mahal2, colour)

    def from_images(self, background: nn.Module, images: Tensor) -> SparseVoxels:
        """One frame's hull from RGB images ``(C, 3, H, W)`` in [0, 1] against a
        :class:`~torchtrack.background.BackgroundModel` (its ``mahalanobis2_yuv`` and ``normalise``); the voxel
        colours are the model's gain-normalised YUV."""
        check_shape(images, (self.plan.C, 3, self.plan.H, self.plan.W), "images")
        yuv = background.normalise(images[None])[0]  # (C, 3, H, W), YUV and gain computed once
        return self(background.mahalanobis2_yuv(yuv), yuv)


def hierarchical_hull(rig: nn.Module, mahal2: Tensor, colour: Tensor, config: HullConfig) -> SparseVoxels:
    """The hull of one frame: ``HierarchicalHull(rig, config)(mahal2, colour)``. The plan is built on each call;
    for many frames of one rig keep a :class:`HierarchicalHull`."""
    return HierarchicalHull(rig, config)(mahal2, colour)


def _hull(plan: HullPlan, config: HullConfig, min_views: int, mahal2: Tensor, colour: Tensor) -> SparseVoxels:
    """:meth:`HierarchicalHull.forward`."""
    C, H, W = plan.C, plan.H, plan.W
    check_shape(mahal2, (C, H, W), "mahal2")
    check_shape(colour, (C, 3, H, W), "colour")
    for name, x in (("mahal2", mahal2), ("colour", colour)):
        if not x.is_floating_point() or x.device != plan.device:
            raise InputError(f"{name}: expected a floating point tensor on {plan.device} (the plan's device), got "
                             f"{x.dtype} on {x.device}")
    flat, dtype = mahal2.reshape(-1), mahal2.dtype
    footprint = {}  # window -> (C H W,) uint8 foreground mask max-filtered over it (row-offset layout, as flat)
    if config.footprint_early_out:
        fg = (mahal2 > config.footprint_mahalanobis2).to(torch.uint8)  # (C, H, W); NaN: not foreground
        for k in sorted(set(plan.footprint[:-1]) - {1}):
            footprint[k] = _max_filter(_max_filter(fg, k, 1), k, 2).reshape(-1)
    kept: list[tuple[int, Tensor, tuple[Tensor, ...]]] = []  # (level, ijk (K, 3), their samples: idx, d, sees)
    parents, step = None, max(1, _CHUNK_SAMPLES // (64 * C))  # parents per chunk
    for level in range(plan.L + 1):
        many = level > 0 and parents.shape[0] > step
        centre_test = config.centre_sample and 0 < level == plan.L
        chunks = [(plan.ijk0, plan.idx0, plan.sees0)] if level == 0 else (
            _children_samples(plan, level, parents[i:i + step], dtype, centre_test)
            for i in range(0, parents.shape[0], step))
        ijks, labels, stash = [], [], []
        for ijk, idx, sees, *centre in chunks:  # (V, 3), (C, 8, V), (C, V)[, (C, V)]
            d = flat.index_select(0, idx.reshape(-1)).reshape(idx.shape).clamp_(max=config.clip_mahalanobis2)
            m = d.sum(1) / 8  # (C, V)
            s = (d * d).sum(1) / 8 - m * m  # population variance of the 8 samples
            sees = sees & torch.isfinite(m)
            m_edge = None
            if centre:  # the finest edge rule on 9 samples: the centre breaks a 4 : 4 tie (a NaN centre does not)
                m_edge = (m * 8 + flat.index_select(0, centre[0].reshape(-1)).reshape(m.shape)
                          .clamp(max=config.clip_mahalanobis2)) / 9
                m_edge = torch.where(torch.isfinite(m_edge), m_edge, m)
            near_fg = None
            if plan.footprint[level] in footprint:
                window = footprint[plan.footprint[level]]
                near_fg = window.index_select(0, idx.reshape(-1)).reshape(idx.shape).amax(1).bool()  # (C, V)
            label = _classify(m, s, sees, config, min_views, level == plan.L, near_fg, m_edge)
            if many:  # keep only what the colours may need
                rows = ((label == _FG) | (label == _UNKNOWN)).nonzero()[:, 0]
                idx, d, sees = _take(idx, rows), _take(d, rows), sees[:, rows]
            ijks.append(ijk)
            labels.append(label)
            stash.append((idx, d, sees))
        ijk, label = (ijks[0], labels[0]) if len(ijks) == 1 else (torch.cat(ijks), torch.cat(labels))
        idx, d, sees = stash[0] if len(stash) == 1 else (torch.cat(x, -1) for x in zip(*stash))
        rows = ((label == _FG) | (label == _UNKNOWN)).nonzero()[:, 0] if many else None  # the stashed voxels
        label = _resolve_unknown(plan, level, ijk, label, kept)
        keep = (label == _FG).nonzero()[:, 0]  # (K,)
        if keep.numel():
            at = keep if rows is None else torch.searchsorted(rows, keep)
            kept.append((level, ijk[keep], (_take(idx, at), _take(d, at), sees[:, at])))
        parents = ijk[label == _EDGE]
        if parents.shape[0] == 0:
            break
    return _assemble(plan, kept, dtype, colour, config.t_low)


def _assemble(plan: HullPlan, kept: list[tuple[int, Tensor, tuple[Tensor, ...]]], dtype: torch.dtype, colour: Tensor,
              t_low: float) -> SparseVoxels:
    """The kept voxels of all levels as :class:`SparseVoxels`, their colours from their samples in one pass."""
    dev, C = plan.device, plan.C
    if not kept:
        empty = (torch.zeros(C, 8, 0, dtype=torch.int32, device=dev), torch.zeros(C, 8, 0, dtype=dtype, device=dev),
                 torch.zeros(C, 0, dtype=torch.bool, device=dev))
        kept = [(0, torch.zeros(0, 3, dtype=torch.long, device=dev), empty)]
    centres = torch.cat([plan.lower_t + (ijk + 0.5) * plan.edge(k) for k, ijk, _ in kept])
    sizes = torch.cat([torch.full((ijk.shape[0],), plan.edge(k), device=dev) for k, ijk, _ in kept])
    levels = torch.cat([torch.full((ijk.shape[0],), k, dtype=torch.long, device=dev) for k, ijk, _ in kept])
    idx, d, sees = (x[0] if len(kept) == 1 else torch.cat(x, -1) for x in zip(*(smp for _, _, smp in kept)))
    colours = _colours(colour, idx, d, sees, t_low, plan.pixel0)
    n_fine = tuple(n * 2 ** plan.L for n in plan.n0)
    return SparseVoxels(centres.to(dtype), sizes.to(dtype), colours, levels, tuple(plan.lower),
                        plan.edge(plan.L), n_fine)


def hull_from_images(rig: nn.Module, background: nn.Module, images: Tensor, config: HullConfig) -> SparseVoxels:
    """The hull of one frame of RGB images: ``HierarchicalHull(rig, config).from_images(background, images)``
    (the plan built on each call)."""
    return HierarchicalHull(rig, config).from_images(background, images)
