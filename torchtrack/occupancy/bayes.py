"""Bayesian occupancy grid: every pixel a noisy sensor, fused over cameras (de Bem eq. 1-8, Franco & Boyer).

Per camera i and pixel p, with F the silhouette detection, S "the pixel samples the voxel" and R "another
object on the viewing line" (ALGORITHMS.md §1):

    p(F=1 | G=1) = P_S0 / 2 + P_S1 * PD
    p(F=1 | G=0) = P_S0 / 2 + P_S1 * (P_R1 * PD + P_R0 * PFA)
    p(I | G)     = p(F=1 | G) U(I) + p(F=0 | G) N(I; mu_p, Sigma_p)

and the posterior log-odds of voxel X sum, over cameras and over the k x k window around X's projection,
the per-pixel ratio log p(I|G=1) - log p(I|G=0) (Algorithm 1: the product of the window's pixel terms).
Everything inside the sum depends on the pixel alone, so it is computed once per image, box-summed over the
window, and gathered at each voxel's pixel through a lookup table fixed for the rig: one gather per voxel
and camera (the tracker's :meth:`BayesianGrid.occupied_voxels` gathers three cameras first, and the rest only
where those leave the voxel a chance). Voxels outside a camera's image get nothing from it; voxels that fewer
than ``min_views`` cameras see are reported unobserved.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.occupancy.grid import GridSpec, VoxelLookup

#: ``BayesConfig.pd`` (None) of a rig with fewer than ``MANY_CAMERAS`` cameras, and the default for every rig. A
#: pixel that clearly shows its background then outweighs seven that clearly show foreground (log ratios -1.96 and
#: +0.25): up to eight cameras the grid is the silhouettes' intersection, the tightest volume, which few cameras
#: need against phantoms.
PD_FEW_CAMERAS = 0.99
#: ``BayesConfig.pd`` (None) of a rig with ``MANY_CAMERAS`` cameras or more. At 0.95 (log ratios -1.33 and +0.25)
#: six cameras' foreground outweighs one camera's background, so a voxel is kept where one view alone sees clothing
#: against a background of its colour, at the cost of a fatter volume; with fewer cameras there is no such
#: majority, and the lower value only fattens the soft margins of a phantom-prone grid (docs/results.md,
#: "Robustness", the sensor model).
PD_MANY_CAMERAS = 0.95
#: The fewest cameras for ``PD_MANY_CAMERAS``: at 0.95 a single miss is outvoted where six or more views see
#: foreground, so a rig of seven is the first where a voxel seen by every camera can have one view miss it.
MANY_CAMERAS = 7
#: :meth:`BayesianGrid.occupied_voxels` sums each voxel's evidence over this many of the cameras that see it first
#: (spread round the rig), and the rest only where those leave it a chance: at the default sensor models two views'
#: strong background outweighs the foreground of up to ten others, so most of a wide volume is settled by three
#: gathers instead of one per camera (scripts/bench_capture_volume.py; docs/results.md, "Speed").
FIRST_VIEWS = 3
#: :meth:`BayesianGrid.occupied_voxels` sums every camera where the first views' bound comes within this of the
#: threshold's log-odds: far above the rounding of a float32 sum of a few terms, so that the rounding never drops a
#: voxel that the full sum keeps.
BOUND_MARGIN = 1e-3


def default_pd(num_cameras: int) -> float:
    """The detection probability ``BayesConfig.pd`` takes when not given, for a rig of ``num_cameras``."""
    return PD_MANY_CAMERAS if num_cameras >= MANY_CAMERAS else PD_FEW_CAMERAS


@dataclass(frozen=True)
class BayesConfig:
    """Sensor model of the Bayesian grid.

    The defaults are not the paper's uniform priors (P_S1 = P_R1 = 1/2, which make the fusion a soft
    majority vote, fat on a single person: scripts/eval_occupancy.py, docs/results.md, "Occupancy"): for one person,
    a voxel inside another camera's silhouette cone but off the body is usually empty while its pixel still
    sees the body, so a detection is mostly explained by another object on the viewing line (P_R1 = 0.75)
    and a background pixel is strong evidence against occupancy. ``window`` 1 gives the tightest grid on
    exact calibrations; 3 (the paper's k x k window) tolerates a pixel of calibration error at a small cost
    in recall.

    Attributes:
        pd: detection probability P(F=1 | the pixel samples an occupied voxel); None: from the rig's number of
            cameras (:func:`default_pd`: 0.99 below seven cameras, 0.95 from seven, where the other views outvote
            one view's miss; the tracking config's choice: a limb matters more there than a tight volume).
        pfa: false-alarm probability P(F=1 | nothing there).
        p_sample: P(S=1), the pixel samples the voxel.
        p_other: P(R=1), another object on the viewing line.
        window: k of the k x k sampling window (odd).
        prior: prior occupancy probability of a voxel.
        min_views: voxels seen by fewer cameras are unobserved (None: all cameras).
        shadow_layer_m: voxels whose centre lies less than this above the grid's floor take their evidence from
            the background model with its shadow test (``BackgroundConfig.shadow_min_gain``), the others without
            it. A floor shadow seen by every camera carves a ghost slab in this layer around the feet, while grey
            or dark clothing, which the shadow test cannot tell from a shadow on a lighter floor or wall, is kept
            everywhere above it (0: no shadow test; docs/results.md, "Occupancy").
        shadow_min_share: a floor-layer voxel takes the shadow test's evidence only where at least this share of
            the cameras that see foreground there see a shadow: a cast shadow's ghost voxel shows shadow to each
            camera whose view of it the body does not block, while a foot low in contrast with the floor is taken
            for shadow by some cameras only, and a single camera's background vote outweighs up to seven
            others' foreground at ``pd`` 0.99, five at 0.95 (docs/results.md, "Robustness", Shadows). 0: every
            camera's shadow counts.
    """

    pd: float | None = 0.99
    pfa: float = 0.1
    p_sample: float = 0.95
    p_other: float = 0.75
    window: int = 1
    prior: float = 0.5
    min_views: int | None = None
    shadow_layer_m: float = 0.2
    shadow_min_share: float = 0.5

    def __post_init__(self) -> None:
        for name in ("pd", "pfa", "p_sample", "p_other", "prior"):
            v = getattr(self, name)
            if v is None and name == "pd":
                continue
            if not 0.0 < v < 1.0:
                raise InputError(f"BayesConfig.{name} must be in (0, 1), got {v}")
        if self.window < 1 or self.window % 2 == 0:
            raise InputError(f"BayesConfig.window must be a positive odd number, got {self.window}")
        if not self.shadow_layer_m >= 0:
            raise InputError(f"BayesConfig.shadow_layer_m must be >= 0, got {self.shadow_layer_m}")
        if not 0 <= self.shadow_min_share <= 1:
            raise InputError(f"BayesConfig.shadow_min_share must be in [0, 1], got {self.shadow_min_share}")

    def detection_probabilities(self) -> tuple[float, float]:
        """(p(F=1 | G=1), p(F=1 | G=0))."""
        if self.pd is None:
            raise InputError("BayesConfig.pd is None: resolve it for the rig first (default_pd)")
        s1, r1 = self.p_sample, self.p_other
        return (1 - s1) / 2 + s1 * self.pd, (1 - s1) / 2 + s1 * (r1 * self.pd + (1 - r1) * self.pfa)


def pixel_log_ratio(log_bg: torch.Tensor, log_uniform: float, config: BayesConfig) -> torch.Tensor:
    """Per-pixel evidence log p(I|G=1) - log p(I|G=0).

    Args:
        log_bg: (...) log N(I; mu, Sigma) of each pixel under its background Gaussian.
        log_uniform: log U(I), the uniform foreground colour density.

    Returns:
        (...) the log ratio; NaN stays NaN (unreadable pixels).
    """
    f1, f0 = config.detection_probabilities()
    # log(f U + (1 - f) N) = log U + log f + softplus(x + log((1 - f) / f)), x = log N - log U
    x = log_bg - log_uniform
    return (math.log(f1 / f0) + F.softplus(x + math.log((1 - f1) / f1))
            - F.softplus(x + math.log((1 - f0) / f0)))


def shadow_votes(lit: torch.Tensor, shadowed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-camera evidence of voxels without and with the shadow test, (B, C, L) each -> (B, L) how many cameras
    see a shadow there (foreground without the test, background with it) and how many see foreground without it
    (``BayesConfig.shadow_min_share``)."""
    foreground = lit > 0
    return (foreground & (shadowed < 0)).sum(1), foreground.sum(1)


def window_sum(x: torch.Tensor, k: int) -> torch.Tensor:
    """(B, C, H, W) -> (B, C, H, W) sum over the k x k window around each pixel (zeros beyond the border)."""
    if k == 1:
        return x
    B, C, H, W = x.shape
    s = F.avg_pool2d(x.reshape(B * C, 1, H, W), k, stride=1, padding=k // 2, count_include_pad=True)
    return (s * (k * k)).reshape(B, C, H, W)


@dataclass(frozen=True)
class Occupancy:
    """Output of an occupancy model on a batch of frames.

    Attributes:
        log_odds: (B, V) posterior log-odds of occupancy (logit of the prior where unobserved).
        observed: (V,) bool, voxels seen by at least ``min_views`` cameras.
        spec: the grid.
    """

    log_odds: torch.Tensor
    observed: torch.Tensor
    spec: GridSpec

    def probability(self) -> torch.Tensor:
        """(B, V) P(occupied); 0 where unobserved."""
        return torch.sigmoid(self.log_odds) * self.observed

    def occupied(self, threshold: float = 0.5) -> torch.Tensor:
        """(B, V) bool, P > threshold and observed."""
        return (self.log_odds > math.log(threshold / (1 - threshold))) & self.observed


class BayesianGrid(nn.Module):
    """The Franco-Boyer occupancy grid over ``spec`` for a static ``rig``, batched over frames.

    Args:
        rig: the CameraRig (all cameras one image size, that of the frames given to :meth:`forward`).
        spec: the voxel grid.
        background: a ``BackgroundModel`` of the same cameras and image size.
        config: sensor model (``pd`` None: :func:`default_pd` of the rig; ``self.config`` holds the value used).
    """

    def __init__(self, rig: nn.Module, spec: GridSpec, background: nn.Module, config: BayesConfig = BayesConfig()
                 ) -> None:
        super().__init__()
        if config.pd is None:
            config = replace(config, pd=default_pd(rig.num_cameras))
        self.config = config
        self.spec = spec
        self.camera_names = list(rig.names)
        self.lookup = VoxelLookup(rig, spec)  # checks that all cameras share one image size
        self.image_size_wh = tuple(int(v) for v in rig.image_size_wh[0])
        self.background = background
        need = rig.num_cameras if config.min_views is None else config.min_views
        self.register_buffer("observed", self.lookup.num_views >= need, persistent=False)
        low = spec.centres(dtype=torch.float64)[:, 2] < spec.lower_m[2] + config.shadow_layer_m  # (V,)
        self.register_buffer("floor_layer", low.to(self.observed.device), persistent=False)
        self.register_buffer("floor_index", low.nonzero()[:, 0].to(self.observed.device), persistent=False)
        self._first_views(rig)

    def _first_views(self, rig: nn.Module) -> None:
        """Buffers of :meth:`occupied_voxels`: the observed voxels (``observed_index``, (O,), the floor layer's
        first: ``observed_floor`` of them), the flat pixel index (:attr:`VoxelLookup.flat_index`) of each one's
        first ``FIRST_VIEWS`` cameras that see it (``first_flat``, (k, O), the fill entry where fewer see it) and
        how many other cameras see it (``other_views``, (O,)). The cameras are taken in farthest-point order of
        their centres, so the first views of a voxel look at it from far apart and their cones cross in little
        volume."""
        C, V = len(self.camera_names), self.spec.num_voxels
        centres = rig.centers().detach().double().cpu()  # (C, 3)
        order = [0]
        while len(order) < C:  # farthest-point order: each next camera the farthest from those taken
            d = torch.cdist(centres, centres[order]).min(dim=1).values
            d[order] = -1.0
            order.append(int(d.argmax()))
        low = (self.observed & self.floor_layer).nonzero()[:, 0]
        index = torch.cat([low, (self.observed & ~self.floor_layer).nonzero()[:, 0]])  # (O,)
        seen = self.lookup.pixel_index[order][:, index] >= 0  # (C, O) in that order
        rank = seen.long().cumsum(0) - 1  # (C, O) place of each seeing camera among the voxel's
        k = min(FIRST_VIEWS, C)
        slot = torch.where(seen & (rank < k), rank, k)  # (C, O): row k takes every camera past the first k
        camera = torch.full((k + 1, index.numel()), -1, dtype=torch.long, device=index.device)
        order_t = torch.tensor(order, device=index.device)[:, None].expand_as(slot)
        camera = camera.scatter_(0, slot, order_t)[:k]  # (k, O) each voxel's first k seeing cameras, -1: none
        flat = self.lookup.flat_index.view(C, V)
        fill = flat.new_full((), C * self.image_size_wh[0] * self.image_size_wh[1])
        self.observed_floor = int(low.numel())
        self.register_buffer("observed_index", index, persistent=False)
        self.register_buffer("first_flat", torch.where(camera >= 0, flat[camera.clamp(min=0), index[None]], fill),
                             persistent=False)
        self.register_buffer("other_views", (self.lookup.num_views[index] - (camera >= 0).sum(0)).to(
            self.lookup.pixel_index.device, torch.get_default_dtype()), persistent=False)

    def evidence(self, images: torch.Tensor) -> torch.Tensor:
        """(B, C, 3, H, W) RGB -> (B, C, H, W) window-summed per-pixel log ratio; 0 for unreadable pixels."""
        W, H = self.image_size_wh
        check_shape(images, ("B", len(self.camera_names), 3, H, W), "images")
        return self.pixel_evidence(self.background.log_likelihood(images))  # without the shadow test

    def pixel_evidence(self, log_bg: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) background log-likelihood -> (B, C, H, W) window-summed per-pixel log ratio of occupancy
        (> 0: the pixel says foreground); 0 for unreadable pixels."""
        r = pixel_log_ratio(log_bg, self.background.log_uniform, self.config)
        return window_sum(torch.nan_to_num(r, nan=0.0), self.config.window)

    def floor_evidence(self, log_bg: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) background log-likelihood -> (B, C, L) each camera's evidence (:meth:`evidence`'s log
        ratio) for the floor layer's voxels (``floor_index``); 0 where the camera does not see the voxel."""
        ev = self.pixel_evidence(log_bg).flatten(2)  # (B, C, H * W)
        pix = self.lookup.pixel_index[:, self.floor_index]  # (C, L)
        return ev.gather(2, pix.clamp(min=0)[None].expand(ev.shape[0], -1, -1)) * (pix >= 0)

    def forward(self, images: torch.Tensor) -> Occupancy:
        """Occupancy of a batch of frames.

        Args:
            images: (B, C, 3, H, W) RGB in [0, 1]; NaN frames (unreadable) contribute no evidence.

        Returns:
            :class:`Occupancy` with log_odds (B, V).
        """
        W, H = self.image_size_wh
        check_shape(images, ("B", len(self.camera_names), 3, H, W), "images")
        lit, shadowed, _ = self.background.log_likelihood_and_yuv(images, shadows=self.config.shadow_layer_m > 0)
        return self.from_log_likelihood(lit, shadowed)

    def from_log_likelihood(self, log_bg: torch.Tensor, log_bg_shadows: torch.Tensor | None = None) -> Occupancy:
        """Occupancy from the background log-likelihood of every pixel, ``(B, C, H, W)`` (NaN: no evidence),
        for callers that computed it already (:meth:`BackgroundModel.log_likelihood_and_yuv`); with
        ``log_bg_shadows`` (the same with the shadow test) the voxels of the floor layer (``shadow_layer_m``)
        take theirs from it."""
        prior = math.log(self.config.prior / (1 - self.config.prior))
        log_odds = self.lookup.gather_sum(self.pixel_evidence(log_bg)) + prior  # (B, V)
        if log_bg_shadows is not None and self.floor_index.numel():
            log_odds = log_odds.index_copy(1, self.floor_index, self._floor_sum(log_bg, log_bg_shadows) + prior)
        return Occupancy(log_odds, self.observed, self.spec)

    def _floor_sum(self, log_bg: torch.Tensor, log_bg_shadows: torch.Tensor | None) -> torch.Tensor:
        """(B, L) the floor layer's evidence summed over the cameras: with ``log_bg_shadows``, the shadow test's
        where enough of the cameras that see foreground there see a shadow (``shadow_min_share``)."""
        lit = self.floor_evidence(log_bg)  # (B, C, L)
        if log_bg_shadows is None:
            return lit.sum(1)
        shadowed = self.floor_evidence(log_bg_shadows)
        votes, seeing = shadow_votes(lit, shadowed)
        use = votes >= self.config.shadow_min_share * seeing  # the shadow's evidence where enough cameras agree
        return torch.where(use, shadowed.sum(1), lit.sum(1))

    def _flat_evidence(self, log_bg: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) background log-likelihood -> (B, C*H*W + 1) :meth:`pixel_evidence` of every camera's
        pixels in a row and the fill entry (0) last, as :attr:`VoxelLookup.flat_index` indexes it."""
        ev = self.pixel_evidence(log_bg)
        return torch.cat([ev.reshape(ev.shape[0], -1), ev.new_zeros(ev.shape[0], 1)], dim=1)

    def first_views_bound(self, flat: torch.Tensor, floor_only: bool = False) -> torch.Tensor:
        """(B, C*H*W + 1) evidence as :meth:`_flat_evidence` gives it -> (B, O) an upper bound of the summed
        evidence of each observed voxel (``observed_index``; the prior not included): its first ``FIRST_VIEWS``
        views' evidence plus, for each other camera that sees it, the largest pixel evidence of any camera in the
        frame. ``floor_only``: the floor layer's voxels alone, (B, ``observed_floor``)."""
        C = len(self.camera_names)
        n = self.observed_floor if floor_only else self.observed_index.numel()
        most = flat[:, :-1].reshape(flat.shape[0], C, -1).amax(2).clamp(min=0).amax(1)  # (B,)
        bound = flat[:, self.first_flat[0, :n]]  # (B, n)
        for slot in range(1, self.first_flat.shape[0]):
            bound += flat[:, self.first_flat[slot, :n]]
        return bound.add_(most[:, None] * self.other_views[:n])

    def occupied_voxels(self, log_bg: torch.Tensor, log_bg_shadows: torch.Tensor | None = None,
                        threshold: float = 0.5) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """The voxels whose P(occupied) exceeds ``threshold``, as :meth:`from_log_likelihood` gives them, without
        summing every camera at every voxel: a voxel is dropped where its bound (:meth:`first_views_bound`: its
        first ``FIRST_VIEWS`` views' evidence and the most the others could add; in the floor layer, under both
        the plain and the shadow test's evidence) cannot reach the threshold, and the voxels left are summed over
        every camera. The bound holds for any evidence, so the voxels are :meth:`from_log_likelihood`'s and their
        probabilities agree to rounding (the last place: the sigmoid's vector lanes fall elsewhere).

        Args:
            log_bg, log_bg_shadows: as :meth:`from_log_likelihood`, ``(B, C, H, W)``.
            threshold: in (0, 1).

        Returns:
            per frame: (indices into the grid's voxels (n,), their P(occupied) (n,)), the indices ascending.
        """
        if not 0.0 < threshold < 1.0:
            raise InputError(f"occupied_voxels: threshold must be in (0, 1), got {threshold}")
        B, C = log_bg.shape[:2]
        prior = math.log(self.config.prior / (1 - self.config.prior))
        cut = math.log(threshold / (1 - threshold))
        least = cut - prior - BOUND_MARGIN
        lit = self._flat_evidence(log_bg)  # (B, C*H*W + 1)
        maybe = self.first_views_bound(lit) > least  # (B, O)
        L = self.observed_floor
        shadows = log_bg_shadows is not None and L > 0
        if shadows:  # the floor layer takes the shadow test's evidence where the cameras' vote says so
            shadowed = self._flat_evidence(log_bg_shadows)
            maybe[:, :L] |= self.first_views_bound(shadowed, floor_only=True) > least
        rows, cols = maybe.nonzero(as_tuple=True)  # (n,) each, rows ascending
        full = self.lookup.flat_index.view(C, -1)[:, self.observed_index[cols]]  # (C, n)
        ev = lit[rows[None], full]  # (C, n) every camera's evidence
        total = ev.sum(0)
        if shadows:
            low = (cols < L).nonzero()[:, 0]
            ev_shadowed = shadowed[rows[low][None], full[:, low]]  # (C, m)
            votes, seeing = shadow_votes(ev[:, low].T[:, :, None], ev_shadowed.T[:, :, None])  # (m, 1) each
            use = (votes >= self.config.shadow_min_share * seeing)[:, 0]
            total[low] = torch.where(use, ev_shadowed.sum(0), total[low])
        p = torch.sigmoid(total + prior)
        keep = p > threshold
        rows, vox, p = rows[keep], self.observed_index[cols[keep]], p[keep]
        counts = torch.bincount(rows, minlength=B).tolist()
        out = []
        for idx, pb in zip(vox.split(counts), p.split(counts)):
            order = idx.argsort()
            out.append((idx[order], pb[order]))
        return out
