"""Per-pixel YUV Gaussian background model (Caillette & Howard 2004, §3.2; de Bem et al. 2015).

Conventions of this module:

* Colour space: YUV from :func:`kornia.color.rgb_to_yuv` (BT.470 M/PAL: ``Y = 0.299 R + 0.587 G + 0.114 B``,
  ``U = -0.147 R - 0.289 G + 0.436 B``, ``V = 0.615 R - 0.515 G - 0.100 B``). Images come in as RGB in [0, 1].
* Diagonal covariance: each pixel of each camera has a mean ``mean_yuv`` and a per-channel std ``std_yuv``,
  both ``(C, 3, H, W)``. The stored std is final: floored at ``min_std`` on every channel, **then** Y multiplied by
  ``luminance_relax`` (Caillette: a relaxed luminance variance keeps shadows and illumination changes out of
  the foreground). Flooring first means the relaxation is never absorbed by the floor.
* Shadows (``shadow_min_gain``; ``shadows=True`` in :meth:`BackgroundModel.mahalanobis2` and the like): a cast
  shadow darkens a surface without changing its chromaticity, i.e. it scales the background's YUV by one factor
  ``alpha`` (Horprasert et al. 1999's brightness distortion). Each pixel is then also scored against ``alpha B``
  with the ``alpha`` in ``[shadow_min_gain, 1]`` that fits it best (closed form, unrelaxed std), and the better of
  the two background densities is kept. Grey or dark clothing over a lighter floor or wall is such a darker copy
  of its colour too, but not of its texture: the shadow must also keep the background's texture over a small
  window (``shadow_min_ncc``), where the background has any. Where it has none a pixel cannot tell, so the
  Bayesian grid uses the shadow-tolerant evidence only for the voxels near the floor, where a shadow's ghost
  volume lies (:class:`torchtrack.occupancy.BayesConfig`'s ``shadow_layer_m``).
* Global gain (``compensate_gain``): for each frame and camera, ``g = median_p(Y_frame / Y_mean)`` over the
  pixels with ``Y_mean >= DARK_Y``, clamped to ``GAIN_RANGE`` (warning, naming the camera, when it had to be).
  A global gain multiplies RGB, hence Y, U and V: the whole YUV image is divided by ``g``. The likelihood is
  the density of the *observed* YUV under ``I = g B``, ``B ~ N(mean, diag std^2)``, i.e. it includes the
  Jacobian ``-3 log g`` so that it stays comparable with :attr:`BackgroundModel.log_uniform`.
* Dead frames: a camera frame that is all NaN (not decoded) or all black (every value < 1/255) carries no
  signal. When estimating, such frames are skipped (a camera with too few usable frames is an ``InputError``
  naming it); at run time, they give NaN for that camera, with a warning naming it.
* Recommended foreground test: ``mahalanobis2(images) > FOREGROUND_MAHALANOBIS2``.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from torchtrack.background import estimate as est
from torchtrack.background import static
from torchtrack.checks import InputError, ShapeError, check_shape

if TYPE_CHECKING:
    from torchtrack.io.sequence import SequenceFolder

logger = logging.getLogger(__name__)

#: Recommended foreground threshold on :meth:`BackgroundModel.mahalanobis2` (squared Mahalanobis distance,
#: 3 colour channels). With the floors of :class:`BackgroundConfig` in-noise pixels sit far below it (the
#: chi-square(3) tail above 16 is 0.1 %); see tests/test_background.py for the measured silhouette IoU.
FOREGROUND_MAHALANOBIS2 = 16.0
#: Fewest usable frames per camera for :meth:`BackgroundModel.from_frames` / :meth:`~BackgroundModel.from_sequence`.
MIN_FRAMES = 2
MIN_SEQUENCE_FRAMES = 5
#: A moving sequence refined with subject masks keeps its frames' YUV, frames last, when it has at most this many
#: values (1 GiB in float32): each refinement then reads the changed pixels' values instead of converting every
#: frame again (half the time of a refinement's re-estimation on the Pose2Sim demo).
YUV_CACHE_ELEMENTS = 1 << 28

#: The shadow test's texture window (pixels, odd): a cast shadow darkens its background's texture without
#: changing it (``BackgroundConfig.shadow_min_ncc``).
SHADOW_WINDOW = 7
#: The texture test judges a background window whose Y varies enough that the darkest shadow (``shadow_min_gain``
#: times it, plus the pixels' noise) still correlates with it by ``shadow_min_ncc``, times this margin for the
#: window's few samples; over a flatter window a shadow's texture is lost in the noise and the colour decides.
SHADOW_TEXTURE_MARGIN = 1.25


@dataclass(frozen=True)
class BackgroundConfig:
    """How the background model is estimated and applied.

    Attributes:
        min_std: floor on every per-channel std (YUV units); sensor noise is about 2/255.
        luminance_relax: the Y std is multiplied by this after flooring (Caillette §3.2: shadows and illumination
            changes are not foreground).
        shadow_min_ratio: the relaxation holds only for a pixel whose gain-normalised Y lies within
            ``[r, 1 / r]`` times its background's: a shadow or a change of illumination scales the luminance by a
            bounded factor, and a part darker than any shadow (black hair over a light wall) is judged with the
            unrelaxed Y std (see :meth:`BackgroundModel.mahalanobis2_yuv`). 0: the paper's plain relaxation.
        shadow_min_gain: the darkest shadow: with ``shadows=True``, a pixel whose colour is the background's
            scaled by a factor in ``[shadow_min_gain, 1]`` (darker, same chromaticity, up to the per-pixel noise)
            is background. Cast shadows indoors keep about 0.4-0.9 of the light (the range of the shadow detectors
            of Horprasert et al. 1999 and Cucchiara et al. 2003). 1 (the default) turns the test off. It helps
            where the clothes contrast with the floor, but shoes and trousers in the floor's own tones are darker
            copies of it, taken for its shadow whatever the texture or the cameras' vote (the Bayesian grid's
            ``shadow_min_share``), hence off (docs/results.md, "Robustness", Shadows).
        shadow_min_ncc: the shadow test also asks that a shadowed pixel keep its background's texture: over a
            ``SHADOW_WINDOW`` window, the frame's Y and the background's correlate by at least this (normalised
            cross-correlation, as the texture-based shadow detectors of Sanin et al. 2012's survey). Dark shoes or
            trousers over a tiled or patterned floor are darker copies of its colour, not of its texture. Where
            the background is too flat to tell (``SHADOW_TEXTURE_MARGIN``) the colour alone decides. Only with
            ``shadow_min_gain < 1``; 0 turns the texture test off.
        compensate_gain: per frame and camera, divide the YUV image by its robust global gain vs the background
            (also applied to the estimation frames, so the model is in gain-normalised units).
        max_frames: frames used for estimation, evenly sampled over the given ones.
        fill_static_subject: when estimating from a moving sequence, find the parts of the subject that stay in
            place (left in the temporal median) by their colours and paint them out of the background
            (:mod:`torchtrack.background.static`). For a subject who stays in place (a balancing trial, arms
            raised on the spot). Off in this class: on a subject who moves through the scene, whose median is
            clean, it paints out room that looks like the subject, a fatter silhouette
            (``scripts/eval_static_fill.py``); the tracking config turns it on, as its tracks gain far more where a
            subject stays in place than they lose (docs/results.md, "Recordings without empty frames"). No effect
            on a model from empty-scene frames.
        fill_prior_log_odds: the fill's prior log odds of room against subject for a pixel near where the subject
            moved, subtracted from the colour evidence before the graph cut. 0 (even odds) paints out every
            pixel whose colour the subject explains better, skin-toned walls and wooden furniture included, and
            on the Pose2Sim demo fills several bodies' volume away from the body; 1 keeps the volume body-sized
            at the cost of some keypoints' coverage (``scripts/eval_pose2sim_occupancy.py
            --fill-prior-log-odds``; docs/results.md, "Occupancy").
    """

    min_std: float = 0.012
    luminance_relax: float = 3.0
    shadow_min_ratio: float = 0.7
    shadow_min_gain: float = 1.0
    shadow_min_ncc: float = 0.7
    compensate_gain: bool = True
    max_frames: int = 60
    fill_static_subject: bool = False
    fill_prior_log_odds: float = 0.0

    def __post_init__(self) -> None:
        if not (self.min_std > 0 and math.isfinite(self.min_std)):
            raise InputError(f"BackgroundConfig.min_std must be a positive number, got {self.min_std}")
        if not (self.luminance_relax >= 1 and math.isfinite(self.luminance_relax)):
            raise InputError(f"BackgroundConfig.luminance_relax must be >= 1, got {self.luminance_relax}")
        if not 0 <= self.shadow_min_ratio < 1:
            raise InputError(f"BackgroundConfig.shadow_min_ratio must be in [0, 1), got {self.shadow_min_ratio}")
        if not 0 < self.shadow_min_gain <= 1:
            raise InputError(f"BackgroundConfig.shadow_min_gain must be in (0, 1], got {self.shadow_min_gain}")
        if not 0 <= self.shadow_min_ncc <= 1:
            raise InputError(f"BackgroundConfig.shadow_min_ncc must be in [0, 1], got {self.shadow_min_ncc}")
        if not math.isfinite(self.fill_prior_log_odds):
            raise InputError(f"BackgroundConfig.fill_prior_log_odds must be finite, got {self.fill_prior_log_odds}")
        if self.max_frames < MIN_FRAMES:
            raise InputError(f"BackgroundConfig.max_frames must be >= {MIN_FRAMES}, got {self.max_frames}")


def _camera_names(camera_names: Sequence[str] | None, C: int) -> list[str]:
    if camera_names is None:
        return [f"cam{i}" for i in range(C)]
    names = [str(n) for n in camera_names]
    if len(names) != C:
        raise InputError(f"camera_names: {len(names)} names for {C} cameras: {names}")
    return names


def _check_frames(frames: torch.Tensor, min_frames: int) -> None:
    check_shape(frames, (None, None, 3, None, None), "frames")
    if not frames.is_floating_point():
        raise InputError(f"frames: expected float RGB in [0, 1], got dtype {frames.dtype}")
    if frames.shape[0] < min_frames:
        raise InputError(f"frames: need at least {min_frames} frames, got {frames.shape[0]}")
    if frames.shape[1] < 1 or frames.shape[3] < 1 or frames.shape[4] < 1:
        raise ShapeError(f"frames: empty camera or image dimension in shape {tuple(frames.shape)}")


class BackgroundModel(nn.Module):
    """Per-pixel YUV Gaussian background of every camera (diagonal covariance).

    Args:
        mean_yuv: (C, 3, H, W) per-pixel mean (YUV, gain-normalised units).
        std_yuv: (C, 3, H, W) per-pixel std, final (floored and relaxed), > 0.
        config: the :class:`BackgroundConfig` used (``compensate_gain`` applies at run time).
        camera_names: (C,) names for messages; default ``cam0 ..``.

    Attributes:
        mean_yuv, std_yuv: buffers, as above (move with ``.to()``).
        camera_names: (C,) str. config: :class:`BackgroundConfig`.
        log_uniform: log of the uniform colour density over the YUV image of the RGB unit cube.
    """

    mean_yuv: torch.Tensor
    std_yuv: torch.Tensor

    def __init__(self, mean_yuv: torch.Tensor, std_yuv: torch.Tensor, config: BackgroundConfig = BackgroundConfig(),
                 camera_names: Sequence[str] | None = None) -> None:
        super().__init__()
        check_shape(mean_yuv, (None, 3, None, None), "mean_yuv")
        check_shape(std_yuv, tuple(mean_yuv.shape), "std_yuv")
        if not bool((std_yuv > 0).all()):
            raise InputError("std_yuv: every std must be > 0 (NaN or <= 0 found)")
        self.config = config
        self.camera_names = _camera_names(camera_names, mean_yuv.shape[0])
        #: True when estimated from a moving sequence (:meth:`from_sequence`), not from empty-scene frames
        self.from_moving_sequence = False

        self.register_buffer("mean_yuv", mean_yuv)
        self.register_buffer("std_yuv", std_yuv)
        # derived once, used every frame: 1 / std and the Gaussian's log normaliser (C, H, W)
        self.register_buffer("inv_std_yuv", 1.0 / std_yuv, persistent=False)
        self.register_buffer("log_norm", std_yuv.log().sum(1) + 1.5 * math.log(2 * math.pi), persistent=False)

    # ------------------------------------------------------------------------------------------ estimation

    @classmethod
    def from_frames(cls, frames: torch.Tensor, config: BackgroundConfig = BackgroundConfig(),
                    camera_names: Sequence[str] | None = None) -> BackgroundModel:
        """Model from empty-scene frames: per-pixel YUV mean and unbiased std, then floor and relax.

        With ``compensate_gain`` every frame is first divided by its gain against the plain mean, and the mean
        and std are taken over the normalised frames (auto-exposure flicker does not inflate the std).

        Args:
            frames: (N, C, 3, H, W) RGB in [0, 1], N >= 2 (at most ``max_frames`` are used, evenly sampled);
                NaN values are ignored per pixel, all-NaN or all-black camera frames are skipped.

        Raises:
            ShapeError: bad shape. InputError: fewer than 2 usable frames in some camera (named).
        """
        _check_frames(frames, MIN_FRAMES)
        names = _camera_names(camera_names, frames.shape[1])
        frames = est.subsample(frames, config.max_frames)
        dead = est.dead_frames(frames)  # (N, C)
        est.check_cameras(dead, names, MIN_FRAMES, "background frames")
        dtype = est.compute_dtype(frames)
        mean, std = est.nan_mean_std(frames, dead, None, dtype)  # (C, 3, H, W) each
        if config.compensate_gain:
            gains = est.sequence_gains(frames, dead, mean[:, 0], names, "background frames")  # (N, C)
            mean, std = est.nan_mean_std(frames, dead, gains, dtype)
        return cls(mean, est.floor_and_relax(std, config.min_std, config.luminance_relax), config, names)

    @classmethod
    def from_sequence(cls, frames: torch.Tensor, config: BackgroundConfig = BackgroundConfig(),
                      camera_names: Sequence[str] | None = None,
                      subject_masks: torch.Tensor | None = None) -> BackgroundModel:
        """Model from a moving sequence without empty frames: temporal median and ``1.4826 * MAD``.

        Pass 1: per-pixel median over frames; with ``compensate_gain``, each frame's gain against it; the MAD of
        the gain-normalised frames around that median. Pass 2 (ghost reduction): per-frame foreground masks of
        the pass-1 model (``mahalanobis2 > FOREGROUND_MAHALANOBIS2``, dilated by ``max(1, max(H, W) // 160)``
        px); each pixel's median and MAD are re-estimated from the frames where it is not foreground when at
        least ``MIN_CLEAN_FRAMES`` such frames exist (pass 1 is kept elsewhere). A subject standing still for
        most of the sequence still leaves a ghost: pass 2 cannot see it (the ghost is what pass 1 calls
        background). Pass 3 (``fill_static_subject``): the ghost is found by the colours of the subject's
        moving parts and inpainted from the room around it (:mod:`torchtrack.background.static`).

        Known subject: with ``subject_masks`` (where the subject is, or may be, in each frame: a person
        segmentation, a previous track's projected body), each pixel's median and MAD come from the frames where
        it is free of the subject, wherever at least ``MIN_CLEAN_FRAMES`` such frames exist, passes 1-3 only
        elsewhere. The masks are trusted: a pixel they never cover takes the median of all frames (pass 3 may
        have painted it), so anything else that moves, another person too, belongs in them. On the Pose2Sim
        demo, masks drawn around the reference keypoints give a background the tracker does far better on than
        on passes 1-3's (``scripts/eval_pose2sim_tracking.py --init-from-reference --reference-background``;
        docs/results.md, "The real Pose2Sim demo"). :mod:`torchtrack.tracking.refine` derives such masks from
        the track itself.

        Args:
            frames: (N, C, 3, H, W) RGB in [0, 1] (float16 storage is fine), N >= 5; at most ``max_frames`` are
                used, evenly sampled. NaN ignored per pixel; all-NaN / all-black camera frames skipped.
            subject_masks: (N, C, H, W) bool, True where the subject is (or may be), or None.

        Raises:
            ShapeError: bad shape. InputError: fewer than 5 usable frames in some camera (named).
        """
        _check_frames(frames, MIN_SEQUENCE_FRAMES)
        seq = MovingSequence(frames, config, _camera_names(camera_names, frames.shape[1]))
        return cls.from_moving(seq, subject_masks)

    @classmethod
    def from_moving(cls, seq: MovingSequence, subject_masks: torch.Tensor | None = None) -> BackgroundModel:
        """:meth:`from_sequence` of a sequence whose passes 1-3 are done (:class:`MovingSequence`), with
        ``subject_masks`` (N, C, H, W) over its N frames (before their subsampling) or None."""
        mean, std = (seq.mean, seq.std) if subject_masks is None else seq.with_subject_masks(subject_masks)
        model = cls(mean, std, seq.config, seq.names)
        model.from_moving_sequence = True
        return model

    @classmethod
    def from_folder(cls, folder: SequenceFolder, config: BackgroundConfig = BackgroundConfig(),
                    size_wh: tuple[int, int] | None = None, device: torch.device | str | None = None,
                    progress: bool = False) -> BackgroundModel:
        """Model of a :class:`~torchtrack.io.sequence.SequenceFolder`: from its ``background/`` frames when
        present and readable, else estimated from ``max_frames`` evenly spaced video frames
        (:meth:`from_sequence`). Logs (INFO) which, naming the folder.

        Args:
            folder: the sequence folder. size_wh: (W, H) to read at (the model then has that size; scale the
                intrinsics to match). device: where frames and model go (None: CPU). progress: show a progress
            bar over the frames read.
        """
        return cls.from_folder_and_frames(folder, config, size_wh, device, progress)[0]

    @classmethod
    def from_folder_and_frames(cls, folder: SequenceFolder, config: BackgroundConfig = BackgroundConfig(),
                               size_wh: tuple[int, int] | None = None, device: torch.device | str | None = None,
                               progress: bool = False) -> tuple[BackgroundModel, MovingSequence | None]:
        """:meth:`from_folder`, and where the model was estimated from video frames their
        :class:`MovingSequence` (its ``indices`` the frames), which a refinement of the background from a track
        re-uses instead of reading and estimating them again (None: from ``background/`` frames)."""
        frames = folder.background_frames(config.max_frames, device=device, size_wh=size_wh,
                                          progress="background" if progress else None)
        if frames is not None and frames.shape[0] >= MIN_FRAMES:
            logger.info("background of %s: %d empty-scene frames from %s", folder.root, frames.shape[0],
                        folder.root / "background")
            return cls.from_frames(frames, config, folder.camera_names), None
        n = min(config.max_frames, len(folder))
        logger.info("background of %s: no usable background/ frames; estimating it from %d of the %d video "
                    "frames (temporal median, second pass against ghosts)", folder.root, n, len(folder))
        if n < MIN_SEQUENCE_FRAMES:
            raise InputError(f"{folder.root}: no background/ frames and only {len(folder)} video frames; need at "
                             f"least {MIN_SEQUENCE_FRAMES} to estimate the background")
        indices, frames = folder.sample_frames(n, device=device, size_wh=size_wh,
                                               progress="background (estimated)" if progress else None)
        seq = MovingSequence(frames, config, folder.camera_names, indices=indices)
        return cls.from_moving(seq), seq

    # ------------------------------------------------------------------------------------------ evaluation

    @property
    def log_uniform(self) -> float:
        """log U: the uniform density over the YUV image of the RGB unit cube, ``-log |det M_rgb2yuv|``."""
        return est.log_uniform_density()

    @property
    def num_cameras(self) -> int:
        return self.mean_yuv.shape[0]

    def to_yuv(self, images: torch.Tensor) -> torch.Tensor:
        """(..., 3, H, W) RGB -> YUV with :func:`kornia.color.rgb_to_yuv`."""
        check_shape(images, ("...", 3, None, None), "images")
        return est.rgb_to_yuv(images)

    def _check_images(self, images: torch.Tensor) -> None:
        check_shape(images, (None, None, 3, None, None), "images")
        C, _, H, W = self.mean_yuv.shape
        if tuple(images.shape[1:]) != (C, 3, H, W):
            raise ShapeError(f"images: shape {tuple(images.shape)} (B, C, 3, H, W) does not fit the background "
                             f"model's {C} cameras of {H}x{W} (HxW), i.e. (B, {C}, 3, {H}, {W})")

    def gain(self, images: torch.Tensor) -> torch.Tensor:
        """(B, C, 3, H, W) RGB -> (B, C) robust global gain vs the background (clamped, see the module doc); 1
        when ``compensate_gain`` is off; NaN for a dead frame (all NaN or black) or one without usable pixels."""
        return self._normalise(images)[1]

    def normalise(self, images: torch.Tensor) -> torch.Tensor:
        """(B, C, 3, H, W) RGB -> (B, C, 3, H, W) YUV, divided by the frame's gain when ``compensate_gain``;
        NaN for dead camera frames (all NaN or black; warned about, naming the camera)."""
        return self._normalise(images)[0]

    def _normalise(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """YUV (B, C, 3, H, W) as :meth:`normalise`, the (B, C) gain used and the (B, C) dead-frame mask."""
        self._check_images(images)
        dead = est.dead_frames(images)  # (B, C)
        # all-black frames are warned about; all-NaN ones are unreadable, which the reader has said already
        black = dead & ~torch.isnan(images.flatten(2)).all(-1) if bool(dead.any()) else dead
        if bool(black.any()):
            cams = [self.camera_names[c] for c in black.any(0).nonzero()[:, 0].tolist()]
            warnings.warn(f"background model: camera(s) {cams} gave an all-black frame "
                          f"({int(black.sum())} of {black.numel()} camera frames); their output is NaN",
                          RuntimeWarning, stacklevel=3)
        if self.config.compensate_gain:  # the gain needs Y on robust_gain's pixel grid only
            s = est.GAIN_STRIDE
            y = est.rgb_to_yuv(images[..., ::s, ::s])[:, :, 0]  # (B, C, H / s, W / s)
            g = est.robust_gain(y, self.mean_yuv[:, 0, ::s, ::s].to(y), stride=1)  # (B, C)
            g = est.clamp_gain(g.masked_fill(dead, 1.0), self.camera_names, "background model")
        else:
            g = torch.ones(dead.shape, dtype=images.dtype, device=images.device)
        g = g.masked_fill(dead, float("nan"))
        return est.rgb_to_yuv(images, g), g, dead  # (B, C, 3, H, W), the gain folded into the conversion

    def mahalanobis2(self, images: torch.Tensor, shadows: bool = False) -> torch.Tensor:
        """(B, C, 3, H, W) RGB -> (B, C, H, W) squared Mahalanobis distance to each pixel's background,
        ``sum_k ((I_k / g - mean_k) / std_k)^2`` over Y, U, V (Y's std unrelaxed outside the shadow band, see
        :meth:`mahalanobis2_yuv`). NaN where the image is NaN or the frame dead."""
        return self.mahalanobis2_yuv(self._normalise(images)[0], shadows)

    def mahalanobis2_yuv(self, yuv: torch.Tensor, shadows: bool = False) -> torch.Tensor:
        """(..., C, 3, H, W) YUV from :meth:`normalise` -> (..., C, H, W) squared Mahalanobis distance (lets a
        caller that needs both the colours and the distances convert and gain-correct once).

        Where Y is outside ``[r, 1 / r]`` times the background's (``r = shadow_min_ratio``) the Y term uses the
        unrelaxed std, i.e. it is ``luminance_relax^2`` times larger. With ``shadows``, where the shadow model
        explains the pixel better (a higher density, see :meth:`log_likelihood`) it is the distance to the
        shadowed background."""
        return self._mahalanobis2(yuv, shadows)[0]

    @property
    def tests_shadows(self) -> bool:
        """Whether ``shadows=True`` changes anything (``shadow_min_gain < 1``)."""
        return self.config.shadow_min_gain < 1

    def _mahalanobis2(self, yuv: torch.Tensor, shadows: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`mahalanobis2_yuv` (..., C, H, W) and the log normaliser's correction (..., C, H, W) of the model
        that gave it (``log luminance_relax`` where the Y std is unrelaxed), or None when it is 0 everywhere."""
        mean = self.mean_yuv.to(device=yuv.device, dtype=yuv.dtype)
        inv_std = self.inv_std_yuv.to(device=yuv.device, dtype=yuv.dtype)
        z = (yuv - mean) * inv_std  # (..., C, 3, H, W)
        d2 = z.square().sum(-3)
        r, relax = self.config.shadow_min_ratio, self.config.luminance_relax
        log_relax = math.log(relax)
        corr = None
        if r > 0 and relax > 1:
            y, y_bg = yuv[..., 0, :, :], mean[:, 0]
            unrelaxed = (y < r * y_bg) | (r * y > y_bg)  # (..., C, H, W); NaN: False
            d2 = d2 + (relax * relax - 1.0) * z[..., 0, :, :].square() * unrelaxed
            corr = unrelaxed.to(d2.dtype) * log_relax
        lo = self.config.shadow_min_gain
        if not shadows or lo >= 1:
            return d2, corr
        # the shadowed background alpha * mean, alpha fitted in closed form (weighted least squares over Y, U, V
        # with the unrelaxed std) and clamped to the shadow's range
        inv_sh = inv_std * inv_std.new_tensor([relax, 1.0, 1.0])[:, None, None]  # (C, 3, H, W)
        w = mean * inv_sh.square()
        alpha = ((yuv * w).sum(-3) / (mean * w).sum(-3).clamp(min=1e-12)).clamp(lo, 1.0)  # (..., C, H, W)
        d2_sh = ((yuv - alpha.unsqueeze(-3) * mean) * inv_sh).square().sum(-3)
        # log density up to the common -log_norm: -d2 / 2 + correction; the shadow's std is the unrelaxed one
        base = d2 if corr is None else d2 - 2.0 * corr
        shadow = d2_sh - 2.0 * log_relax < base  # NaN: False
        if self.config.shadow_min_ncc > 0:
            shadow = shadow & self.keeps_texture(yuv[..., 0, :, :])
        d2 = torch.where(shadow, d2_sh, d2)
        corr_sh = torch.full_like(d2, log_relax)
        corr = torch.where(shadow, corr_sh, corr_sh.new_zeros(()) if corr is None else corr)
        return d2, corr

    def keeps_texture(self, y: torch.Tensor) -> torch.Tensor:
        """(..., C, H, W) gain-normalised Y -> bool, where the frame keeps its background's texture as a shadow
        does: over a ``SHADOW_WINDOW`` window (cut to the image at its edges), the normalised cross-correlation
        of the two is at least ``shadow_min_ncc`` and the frame's window is not flatter than half the darkest
        shadow's; or the background's window is too flat to tell (``SHADOW_TEXTURE_MARGIN``). A NaN in the
        window: False unless the background's window is flat."""
        cfg = self.config
        k = SHADOW_WINDOW
        H, W = y.shape[-2:]

        def box(x: torch.Tensor) -> torch.Tensor:  # window means
            return F.avg_pool2d(x.reshape(-1, 1, H, W), k, stride=1, padding=k // 2,
                                count_include_pad=False).reshape(x.shape)

        b = self.mean_yuv[:, 0].to(y)  # (C, H, W)
        mb = box(b)
        vb = (box(b * b) - mb * mb).clamp(min=0)
        noise = 1.0 / (self.inv_std_yuv[:, 0].to(y) * cfg.luminance_relax)  # the unrelaxed Y std
        rho, gain = cfg.shadow_min_ncc, cfg.shadow_min_gain
        # a shadow's window a * b + noise correlates with b by a s / sqrt(a^2 s^2 + noise^2) (s: b's std)
        snr = math.inf if rho >= 1 else SHADOW_TEXTURE_MARGIN * rho / (gain * math.sqrt(1 - rho * rho))
        flat = vb < (snr * noise) ** 2
        my = box(y)
        vy = (box(y * y) - my * my).clamp(min=0)
        cov = box(y * b) - my * mb  # (..., C, H, W), b broadcast over the leading dims
        # no division: a flat frame window (vy ~ 0) over texture is no shadow, whatever its rounding gives cov
        kept = (vy >= 0.25 * gain * gain * vb) & (cov >= rho * (vy * vb).sqrt())
        return flat | kept

    def log_likelihood(self, images: torch.Tensor, shadows: bool = False) -> torch.Tensor:
        """(B, C, 3, H, W) RGB -> (B, C, H, W) ``log p(I | background)``, a density over YUV space.

        ``log N(I / g; mean, diag std^2) - 3 log g`` (the density of ``I = g B``; ``g = 1`` without gain
        compensation), directly comparable with :attr:`log_uniform`; the Y std unrelaxed outside the shadow band
        (``shadow_min_ratio``, as :meth:`mahalanobis2_yuv`). With ``shadows``, where it is higher, the shadow's
        density ``N(I / g; alpha mean, diag std_unrelaxed^2)`` with the best ``alpha`` in ``[shadow_min_gain, 1]``
        instead (the larger of the two: a shadow is one more way of being background). NaN where the image is NaN
        or dead.
        """
        yuv, g, _ = self._normalise(images)
        return self._log_likelihood(yuv, g, shadows)

    def log_likelihood_and_yuv(self, images: torch.Tensor, shadows: bool = False
                               ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """From one normalisation: :meth:`log_likelihood` (B, C, H, W) without the shadow test, with it when
        ``shadows`` and :attr:`tests_shadows` (else None), and :meth:`normalise` (B, C, 3, H, W)."""
        yuv, g, _ = self._normalise(images)
        lit = self._log_likelihood(yuv, g, False)
        return lit, self._log_likelihood(yuv, g, True) if shadows and self.tests_shadows else None, yuv

    def _log_likelihood(self, yuv: torch.Tensor, g: torch.Tensor, shadows: bool) -> torch.Tensor:
        d2, corr = self._mahalanobis2(yuv, shadows)  # (B, C, H, W)
        log_norm = self.log_norm.to(device=yuv.device, dtype=yuv.dtype)  # (C, H, W)
        log_p = -0.5 * d2 - log_norm - 3.0 * g.log()[:, :, None, None]
        if corr is not None:  # the unrelaxed Gaussian's normaliser where it scored the pixel
            log_p = log_p + corr
        return log_p

    def extra_repr(self) -> str:
        C, _, H, W = self.mean_yuv.shape
        return f"cameras={self.camera_names}, size_hw=({H}, {W}), config={self.config}"


class MovingSequence:
    """A moving sequence's frames with its background's passes 1-3 (:meth:`BackgroundModel.from_sequence`), to be
    refined with subject masks as often as a caller has new ones (:meth:`with_subject_masks`): the background
    refinement re-estimates it from each pass's track (:mod:`torchtrack.tracking.refine`), and passes 1-3, two
    thirds of the work, depend on the frames alone.

    Args:
        frames: (N, C, 3, H, W) RGB in [0, 1]; at most ``config.max_frames`` are used, evenly sampled. names: (C,)
            camera names for messages. refine: False stops after pass 1 (to measure what the second pass brings;
            no fill or masks either). indices: (N,) the frames' indices in their sequence, where known.

    Attributes:
        mean, std: (C, 3, H, W) the background of passes 1-3.
    """

    def __init__(self, frames: torch.Tensor, config: BackgroundConfig, names: Sequence[str], refine: bool = True,
                 indices: Sequence[int] | None = None) -> None:
        _check_frames(frames, MIN_SEQUENCE_FRAMES)
        if indices is not None and len(indices) != frames.shape[0]:
            raise ShapeError(f"MovingSequence: {len(indices)} indices for {frames.shape[0]} frames")
        self.config, self.names, self.refine = config, list(names), refine
        self.indices = None if indices is None else [int(i) for i in indices]
        self.shape = tuple(frames.shape)  # the subject masks' frames are the frames given
        self.frames = frames = est.subsample(frames, config.max_frames)
        self.dead = dead = est.dead_frames(frames)  # (N, C)
        est.check_cameras(dead, names, MIN_SEQUENCE_FRAMES, "sequence frames")
        self.dtype = dtype = est.compute_dtype(frames)
        relax = (config.min_std, config.luminance_relax)
        H, W = frames.shape[-2:]
        gains = None
        if config.compensate_gain:  # gains against the plain median (on a pixel grid: a median of ratios needs few)
            step = max(1, math.ceil(math.sqrt(H * W / est.GAIN_PIXELS)))
            grid = frames[..., ::step, ::step]  # (N, C, 3, H / step, W / step)
            y_ref = est.median_mad(grid, dead, None, dtype, spread=False)[0][:, 0]  # (C, h, w)
            gains = est.sequence_gains(grid, dead, y_ref, names, "sequence frames")  # (N, C)
        self.gains = gains
        self._masked: tuple[torch.Tensor, ...] | None = None  # the last subject masks and their statistics
        # (C, H, W, 3, N) the frames' YUV, for passes 1-3 and every refinement's subject masks
        fits = refine and frames.numel() <= YUV_CACHE_ELEMENTS
        self._yuv = est.frames_last_yuv(frames, dead, gains, dtype) if fits else None
        med, spread, count = self._statistics()  # (C, 3, H, W) each
        std = est.floor_and_relax(spread, *relax)
        self.plain = (med, std, count)  # pass 1: what subject masks that never cover a pixel leave it
        if not refine:
            self.mean, self.std = med, std
            return
        fg = est.foreground_masks(frames, dead, gains, med, std, FOREGROUND_MAHALANOBIS2, max(1, max(H, W) // 160))
        touched = fg.any(0)  # (C, H, W): elsewhere pass 2 would use the same frames as pass 1
        med2, spread2, count = self._statistics(fg, touched)
        use = (count >= est.MIN_CLEAN_FRAMES)[:, None]  # (C, 1, H, W)
        logger.info("background second pass: %.1f%% of the pixels were foreground in some frame, %.1f%% re-estimated "
                    "from their non-foreground frames (mean foreground fraction %.1f%%)",
                    100 * float(touched.float().mean()), 100 * float(use.float().mean()),
                    100 * float(fg.float().mean()))
        mean, std = torch.where(use, med2, med), torch.where(use, est.floor_and_relax(spread2, *relax), std)
        if config.fill_static_subject:
            ghost = static.static_subject(frames, dead, gains, mean, std, FOREGROUND_MAHALANOBIS2, names,
                                          prior_log_odds=config.fill_prior_log_odds)
            mean = static.paint_out(mean, ghost)
        self.mean, self.std = mean, std

    def with_subject_masks(self, subject_masks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and std (C, 3, H, W) from each pixel's frames free of ``subject_masks (N, C, H, W)`` (the frames
        given, before the subsampling to ``max_frames``) wherever at least ``MIN_CLEAN_FRAMES`` are, passes 1-3's
        elsewhere (see ``from_sequence``)."""
        if not self.refine:
            raise InputError("MovingSequence: subject masks refine the background of passes 1-3; this one stopped "
                             "after pass 1 (refine=False)")
        N, C, _, H, W = self.shape
        check_shape(subject_masks, (N, C, H, W), "subject_masks")
        if subject_masks.dtype != torch.bool:
            raise InputError(f"subject_masks: expected a bool tensor, got {subject_masks.dtype}")
        subject_masks = est.subsample(subject_masks, self.config.max_frames).to(self.frames.device)  # the same
        # frames as the frames'. Every pixel, also those the masks never cover (pass 1's median of all frames):
        # the masks override pass 3's fill and pass 2's guesses
        touched = subject_masks.any(0)  # (C, H, W)
        # only the pixels whose masks over the frames changed since the last call are computed again (the
        # refinement's later passes move the track a little: most of the masks stay)
        todo = touched if self._masked is None else touched & (subject_masks != self._masked[0]).any(0)
        med3, spread3, count = self._statistics(subject_masks, todo)
        if self._masked is not None:
            keep = touched & ~todo  # (C, H, W) the same masks as last time: the same statistics
            med3 = torch.where(keep[:, None], self._masked[1], med3)
            spread3 = torch.where(keep[:, None], self._masked[2], spread3)
            count = torch.where(keep, self._masked[3], count)
        self._masked = (subject_masks, med3, spread3, count)
        relax = (self.config.min_std, self.config.luminance_relax)
        plain_med, plain_std, plain_count = self.plain
        mask3 = touched[:, None]  # (C, 1, H, W)
        med3 = torch.where(mask3, med3, plain_med)
        std3 = torch.where(mask3, est.floor_and_relax(spread3, *relax), plain_std)
        use = (torch.where(touched, count, plain_count) >= est.MIN_CLEAN_FRAMES)[:, None]  # (C, 1, H, W)
        logger.info("background from the frames free of the given subject masks at %.1f%% of the pixels",
                    100 * float(use.float().mean()))
        return torch.where(use, med3, self.mean), torch.where(use, std3, self.std)


    def _statistics(self, foreground: torch.Tensor | None = None, pixels: torch.Tensor | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:func:`~torchtrack.background.estimate.median_mad` of the frames, from their YUV kept where it fits
        (``YUV_CACHE_ELEMENTS``; the same values, the same figures), in chunks of pixels as it does."""
        if self._yuv is None:
            return est.median_mad(self.frames, self.dead, self.gains, self.dtype, foreground=foreground,
                                  pixels=pixels)
        C, H, W, _, N = self._yuv.shape
        values = self._yuv.view(-1, 3, N)  # (CHW, 3, N)
        out = torch.full((C * H * W, 3), float("nan"), dtype=self.dtype, device=values.device)
        med, std, count = out, out.clone(), torch.zeros(C * H * W, dtype=torch.long, device=values.device)
        rows = torch.arange(C * H * W, device=values.device) if pixels is None else pixels.flatten().nonzero()[:, 0]
        fg = None if foreground is None else foreground.permute(1, 2, 3, 0).reshape(-1, N)  # (CHW, N)
        step = max(1, est.CHUNK_ELEMENTS // (3 * N))
        for lo in range(0, len(rows), step):
            r = rows[lo:lo + step]
            v = values[r]  # (P, 3, N) a copy
            if fg is not None:
                v.masked_fill_(fg[r][:, None], float("nan"))
            med[r], std[r], count[r] = est.nan_median_mad(v)
        return (med.view(C, H, W, 3).permute(0, 3, 1, 2).contiguous(),
                std.view(C, H, W, 3).permute(0, 3, 1, 2).contiguous(), count.view(C, H, W))


def sequence_statistics(frames: torch.Tensor, config: BackgroundConfig, names: Sequence[str],
                        refine: bool = True, subject_masks: torch.Tensor | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and final std (C, 3, H, W) of a moving sequence, as :meth:`BackgroundModel.from_sequence`.

    Args:
        frames: (N, C, 3, H, W) RGB in [0, 1]. names: (C,) camera names for messages.
        refine: False stops after pass 1 (to measure what the second pass brings; no fill or masks either).
        subject_masks: (N, C, H, W) bool where the subject is, or None (see ``from_sequence``).
    """
    seq = MovingSequence(frames, config, names, refine)
    if subject_masks is None or not refine:
        return seq.mean, seq.std
    return seq.with_subject_masks(subject_masks)
