"""Background re-estimation from the track: track, mask the tracked body, re-estimate, track again.

A sequence without empty frames gets its background from the moving clip (temporal median and MAD,
:meth:`BackgroundModel.from_sequence`). Where the subject covers a pixel in most of the frames, that median
is the subject: a ghost that hides the body where it stands and shows it where it has left. The track says
where the body is in every frame, even when it is imperfect, and that is what each pass of
:func:`track_with_background_refinement` uses:

1. the tracked blobs' ellipsoids, grown by ``blob_scale``, are rendered into every view of the sampled frames
   (:func:`~torchtrack.tracking.clearance.body_masks`, exact ray - ellipsoid hits through the lens model);
2. each pixel's clearance, its distance in pixels to the rendered body, is measured in every frame
   (:func:`~torchtrack.tracking.clearance.clearance_px`);
3. each pixel's background is the median and MAD of its clearest frames
   (:func:`~torchtrack.tracking.clearance.clear_frame_masks`): every
   frame at least ``clear_fraction`` of the image's larger side away from the body, or, where fewer than
   ``clear_frames`` are, its ``clear_frames`` clearest ones
   (``BackgroundModel.from_sequence(..., subject_masks=...)``); a pixel that is never ``near_feet_fraction`` clear
   of the drawn feet keeps the sequence estimate instead (a stance foot that never moves, held a few cm off by the
   track, is otherwise in the clearest frames: the static-subject fill's estimate has the room there);
4. the sequence is tracked again: from the same start where one was given, else from a start searched for
   again on the refined observation (a start found on the first, poorest observation is not kept);
5. of the refined passes, the track that fits its own observation best (``RefineConfig.keep``) is the result.

Ranking the frames instead of trusting the masks is what makes the loop converge from a poor first track: a
limb the track misplaces is still nearer the pixels it covers in the frames the track puts near them; trusting
the grown masks as they are did not converge. The passes need not settle on one track, so the result is the pass
that fits its observation best (step 5), not the last (the passes on the Pose2Sim demo: docs/results.md, "The real
Pose2Sim demo"; the masks trusted: "Tried and dropped").

:func:`background_from_track` does the same re-estimation from a finished track's ``poses.npz``, for observing
the sequence again with it (``torchtrack observe SEQ --background-from-track OUT/poses.npz``).
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from torchtrack.background import BackgroundConfig, BackgroundModel, MovingSequence
from torchtrack.background.estimate import MIN_CLEAN_FRAMES
from torchtrack.background.model import MIN_SEQUENCE_FRAMES
from torchtrack.blobs import BlobModel
from torchtrack.cameras import CameraRig
from torchtrack.checks import InputError, check_shape, config_section
from torchtrack.io.poses import Poses
from torchtrack.io.sequence import SequenceFolder, evenly_spaced
from torchtrack.io.video import DataWarning
from torchtrack.skeleton import Skeleton
from torchtrack.tracking.body_refit import mean_ik_residual_m
from torchtrack.tracking.clearance import PixelTiles, body_masks, clear_frame_masks, clearance_px, stays_near
from torchtrack.tracking.markerless import MarkerlessTracker
from torchtrack.tracking.observation import Observer
from torchtrack.tracking.run import track_sequence
from torchtrack.tracking.stream import ObservationWorker

__all__ = ["RefineConfig", "background_from_track", "refined_background", "track_body", "track_change_m",
           "track_with_background_refinement", "tracked_body"]

log = logging.getLogger(__name__)

#: The bones whose blobs ``RefineConfig.near_feet_fraction`` draws.
FOOT_BONES = ("l_foot", "r_foot")


#: ``RefineConfig.keep``: the best-fitting refined pass, or the last pass.
KEEP_CHOICES = ("fit", "last")


@dataclass(frozen=True)
class RefineConfig:
    """Background refinement settings (the ``background_refinement`` section of a tracking config).

    Attributes:
        passes: re-estimations of the background at most, each followed by a new track (0: track once).
        blob_scale: the blobs' ellipsoids are grown by this factor before they are rendered.
        clear_frames: k: each pixel's background comes from its k clearest frames (ties included) or from more
            (see ``clear_fraction``), never from a frame where the rendered body covers it: where fewer than
            ``MIN_CLEAN_FRAMES`` frames leave a pixel, the sequence estimate (passes 1-3) is kept there.
        clear_fraction: frames at least this fraction of the image's larger side clear of the body all count.
        near_fraction: a pixel with fewer than ``clear_frames`` frames (all of them, when there are fewer) at least
            this fraction of the image's larger side clear of the rendered body keeps the sequence estimate (passes
            1-3, with the static-subject fill) instead: a part of the subject that stays in place just outside the
            drawn body (the toes of a stance foot) is otherwise in all of those frames and so in the background (0:
            off). On the Pose2Sim demo's occupancy it brings the stance foot's toes back and grows the volume
            (docs/results.md, "Occupancy"); between tracking passes it made the track worse, so the tracking config
            leaves it off (docs/results.md, "Tracker settings").
        near_feet_fraction: ``near_fraction`` for the feet alone: a pixel with fewer than ``clear_frames`` frames
            this far from the drawn feet keeps the sequence estimate. A stance foot that never moves is in the
            video's median, which the static-subject fill paints out, but drawn where the track holds it, a few cm
            off, the real foot's pixels are clear of it in every frame, and so back in the background (0: off).
        min_change_m: a pass whose track moved less than this from the one before (:func:`track_change_m`) has
            settled. With ``keep: fit`` only settled passes compete (once there are any); with ``keep: last`` the
            passes stop early at the first that settled without losing a frame the one before tracked: one more
            pass is then the last (0: all ``passes`` are run).
        keep: which pass's track is the result: ``fit``, the settled refined pass (after the first
            re-estimation) whose track fits its own observation best, the fewest lost frames and then the lowest
            mean IK residual (the goals' distance from the fitted skeleton, ``extra['ik_residual_m']``), or the
            best of all refined passes where none settled; ``last``, the last pass. ``fit`` because the passes may
            wander between tracks, which the residual tells apart, rather than settle (docs/results.md, "The real
            Pose2Sim demo"); settled ones only because the residuals of passes whose backgrounds still move
            compare fits to different observations: an early pass's fit to a poor background can be the closest.
        patience: with ``keep: fit``, the passes stop once this many in a row have not bettered the best settled
            pass: a pass that moved little can still be followed by one that moves on to a better track.
        max_fps: the passes track every n-th frame of a sequence faster than this, n = floor(fps / max_fps), and
            the result is tracked once more at the full rate on its background (0: every frame). The passes'
            tracks only serve the background's estimate and the choice of pass, and the tracker's settings are
            measured at 30 frames/s: a 60 frames/s clip's passes cost half (docs/results.md, "Background
            refinement").
    """

    passes: int = 16
    blob_scale: float = 1.3
    clear_frames: int = 10
    clear_fraction: float = 0.04
    near_fraction: float = 0.0
    near_feet_fraction: float = 0.0
    min_change_m: float = 0.01
    keep: str = "fit"
    patience: int = 3
    max_fps: float = 30.0

    def __post_init__(self) -> None:
        for name, kind in (("passes", int), ("clear_frames", int), ("patience", int), ("blob_scale", float),
                           ("clear_fraction", float), ("near_fraction", float), ("near_feet_fraction", float),
                           ("min_change_m", float),
                           ("max_fps", float)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float) if kind is float else int):
                raise InputError(f"background_refinement.{name} must be a number{' (whole)' * (kind is int)}, "
                                 f"got {value!r}")
        if self.passes < 0:
            raise InputError(f"background_refinement.passes must be >= 0, got {self.passes}")
        if self.patience < 1:
            raise InputError(f"background_refinement.patience must be >= 1, got {self.patience}")
        if self.keep not in KEEP_CHOICES:
            raise InputError(f"background_refinement.keep must be one of {list(KEEP_CHOICES)}, got {self.keep!r}")
        if not self.blob_scale >= 1.0:
            raise InputError(f"background_refinement.blob_scale must be >= 1, got {self.blob_scale}")
        if self.clear_frames < MIN_CLEAN_FRAMES:
            raise InputError(f"background_refinement.clear_frames must be >= {MIN_CLEAN_FRAMES} (the fewest "
                             f"frames a pixel's background is estimated from), got {self.clear_frames}")
        if not 0.0 < self.clear_fraction < 1.0:
            raise InputError(f"background_refinement.clear_fraction must be in (0, 1), got {self.clear_fraction}")
        for name in ("near_fraction", "near_feet_fraction"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise InputError(f"background_refinement.{name} must be in [0, 1) (0: off), got "
                                 f"{getattr(self, name)}")
        for name in ("min_change_m", "max_fps"):
            value = getattr(self, name)
            if not (value >= 0 and np.isfinite(value)):
                raise InputError(f"background_refinement.{name} must be >= 0 and finite (0: off), got {value}")

    def frame_step(self, fps: float) -> int:
        """n: the passes track every n-th frame of a sequence of ``fps`` frames a second (``max_fps``; a rate 1 %
        under a multiple counts as it: 59.94 frames/s as 60)."""
        return max(1, int(fps / self.max_fps * 1.01)) if self.max_fps > 0 and np.isfinite(fps) else 1

    @classmethod
    def from_dict(cls, doc: dict[str, Any] | None, source: str = "<config>") -> RefineConfig:
        """Build from the YAML section (None: the defaults), naming unknown keys."""
        return cls(**config_section(cls, doc, source, "background_refinement", " (passes: 0 turns it off)"))


def track_change_m(poses: Poses, before: Poses) -> float:
    """How far a track moved from an earlier one of the same frames: the mean over the frames both tracked of
    the mean distance (m) between their 16 landmarks (NaN when no frame is tracked in both).

    Raises:
        InputError: the two hold different frames.
    """
    if not np.array_equal(poses.frame_index, before.frame_index):
        raise InputError("track_change_m: the two tracks hold different frames")
    both = np.asarray(poses.valid) & np.asarray(before.valid)
    if not both.any():
        return float("nan")
    return float(np.linalg.norm(poses.landmarks()[both] - before.landmarks()[both], axis=-1).mean())


def refined_background(frames: torch.Tensor | MovingSequence, angles: torch.Tensor, rig: CameraRig,
                       skeleton: Skeleton, bg_config: BackgroundConfig, config: RefineConfig,
                       camera_names: list[str] | None = None, blobs: BlobModel | None = None,
                       tiles: PixelTiles | None = None) -> BackgroundModel:
    """The background re-estimated from each pixel's frames clearest of the tracked body (module docstring).

    Args:
        frames: (N, C, 3, H, W) RGB frames of the sequence (float16 is fine), at the rig's size; or a
            :class:`~torchtrack.background.MovingSequence` of them (its config and names are used), which keeps
            the background's passes 1-3 for every refinement pass.
        angles: (N, D) the tracked state vectors of those frames (NaN where untracked).
        skeleton, blobs: the tracked subject's skeleton and blob model (see :func:`body_masks`).
        tiles: the rig's pixel rays, made once for several calls (:class:`PixelTiles`; default: made here).
    """
    N, C, _, H, W = frames.shape
    check_shape(angles, (N, skeleton.num_dofs), "angles")
    clear_px = config.clear_fraction * max(H, W)
    masks = torch.empty((N, C, H, W), dtype=torch.bool)
    angles = angles.to(rig.K.device, torch.float32)
    body = body_masks(rig, skeleton, angles, config.blob_scale, blobs, tiles).cpu()
    near_px = config.near_fraction * max(H, W)
    feet_px = config.near_feet_fraction * max(H, W)
    feet = None
    if feet_px > 0:  # the feet alone, for near_feet_fraction
        feet = body_masks(rig, skeleton, angles, config.blob_scale, blobs, tiles, bones=FOOT_BONES).cpu()
    for c in range(C):  # one camera at a time: the clearance is 4 bytes a pixel and frame
        # clear_frame_masks compares clearances with thresholds up to clear_px and near_px only
        clearance = clearance_px(body[:, c], within_px=max(clear_px, near_px))
        masks[:, c] = clear_frame_masks(clearance, config.clear_frames, clear_px, near_px)
        if feet is not None:  # the pixels that stay near the feet: no frame (the sequence estimate)
            masks[:, c] |= stays_near(clearance_px(feet[:, c], within_px=feet_px), config.clear_frames, feet_px)
    if isinstance(frames, MovingSequence):
        return BackgroundModel.from_moving(frames, masks.to(frames.frames.device))
    return BackgroundModel.from_sequence(frames, bg_config, camera_names, subject_masks=masks.to(frames.device))


def track_body(poses: Poses, source: str = "poses") -> Skeleton | None:
    """The subject's body a track carries (``body_urdf``, as ``torchtrack track`` writes it), None where it has
    none.

    Raises:
        InputError: the track's state vectors (``dof_names``) or its body have other DOFs than the body model.
    """
    generic = Skeleton.from_urdf()
    if list(poses.dof_names) != list(generic.dof_names):
        raise InputError(f"{source}: field 'dof_names' has other DOFs than the body model ({len(poses.dof_names)} "
                         f"vs {len(generic.dof_names)})")
    if "body_urdf" not in poses.extra:
        return None
    body = Skeleton(str(poses.extra["body_urdf"]), source=f"{source}: body_urdf")
    if body.dof_names != generic.dof_names:
        raise InputError(f"{source}: field 'body_urdf' has other DOFs than the body model "
                         f"({len(body.dof_names)} vs {len(generic.dof_names)})")
    return body


def tracked_body(poses: Poses, source: str = "poses") -> Skeleton:
    """The subject's body of a track: :func:`track_body`, else the body model scaled to its ``subject_height_m``.

    Raises:
        InputError: neither field (or a NaN height: a run that fitted no subject), or other DOFs (named).
    """
    body = track_body(poses, source)
    if body is not None:
        return body
    height = float(poses.extra.get("subject_height_m", float("nan")))
    if not 0.5 <= height <= 2.5:
        raise InputError(f"{source}: no subject body (field 'body_urdf') and no usable height (field "
                         f"'subject_height_m': {height}) to draw the tracked body with")
    return Skeleton.from_urdf().scaled_to_height(height)


def background_from_track(folder: SequenceFolder, poses: Poses, bg_config: BackgroundConfig = BackgroundConfig(),
                          config: RefineConfig = RefineConfig(), size_wh: tuple[int, int] | None = None,
                          device: torch.device | str | None = None, source: str = "poses",
                          blob_specs: str | Path | None = None) -> BackgroundModel:
    """The background of ``folder`` re-estimated from the frames clearest of a track's body (a finished
    ``torchtrack track`` run, its ``poses.npz``): what :func:`track_with_background_refinement` does between
    passes, for observing a sequence without empty frames again once it has been tracked.

    The background is estimated from ``bg_config.max_frames`` evenly spaced frames of the track's span of frames.
    A sampled frame the track does not hold, or holds without a state (NaN), is drawn as covering every pixel
    (the body may be anywhere) and so gives no pixel its background; a frame the track lost is drawn at the
    pose the tracker held for it, as between passes.

    Args:
        poses: the track (``frame_index`` into the folder's frames); its body: :func:`tracked_body`.
        size_wh: (W, H) to read and estimate at (default: the calibration's size).
        source: the track's file name, for errors.
        blob_specs: the blob specification the track used (``TrackerConfig.blobs``; default: blobs.yaml).

    Raises:
        InputError: the track holds no frame of the folder, or no body (:func:`tracked_body`); as
            :meth:`BackgroundModel.from_sequence`.
    """
    skeleton = tracked_body(poses, source)
    if (folder.root / "background").is_dir():
        log.warning("%s: has background/ frames; the background is estimated from the video and the track "
                    "instead", folder.root)
    index = np.asarray(poses.frame_index, np.int64)
    if index.size == 0:
        raise InputError(f"{source}: the track holds no frame")
    inside = (index >= 0) & (index < folder.num_frames)
    if not inside.any():
        raise InputError(f"{source}: its frames {int(index.min())}-{int(index.max())} are not frames of "
                         f"{folder.root} ({folder.num_frames} frames)")
    start, stop = int(index[inside].min()), int(index[inside].max()) + 1
    if stop - start < MIN_SEQUENCE_FRAMES:
        raise InputError(f"{source}: the track spans {stop - start} frames of {folder.root}; estimating a background "
                         f"needs at least {MIN_SEQUENCE_FRAMES}")
    rig = (folder.rig if size_wh is None else folder.rig.resized(*size_wh)).float()
    if device is not None:
        rig = rig.to(device)
    W, H = (int(v) for v in rig.image_size_wh[0].tolist())
    indices, frames = folder.sample_frames(bg_config.max_frames, start, stop, device=device, size_wh=(W, H))
    # each sampled frame's row of the track, by frame number (a gap or another order in the track is fine)
    order = np.argsort(index, kind="stable")
    at = np.minimum(np.searchsorted(index[order], indices), index.size - 1)
    row = order[at]  # (N,)
    held = index[row] == np.asarray(indices)
    angles = torch.from_numpy(np.where(held[:, None], np.asarray(poses.angles, np.float32)[row], np.nan))
    return refined_background(frames, angles, rig, skeleton, bg_config, config, folder.camera_names,
                              BlobModel.from_config(skeleton, blob_specs))


def restart(tracker: MarkerlessTracker, state: tuple[torch.Tensor, Skeleton, float | None] | None) -> None:
    """Put ``tracker`` at a pass's start: the given ``(angles, skeleton, floor_z)``, or (None) uninitialised, so
    that the pass searches for its start on its own observation."""
    if state is None:
        tracker.reset()
    else:
        tracker.initialize_from_pose(state[0], skeleton=state[1], floor_z_m=state[2])


def track_with_background_refinement(
        folder: SequenceFolder, background: BackgroundModel, make_observer: Callable[[BackgroundModel], Observer],
        tracker: MarkerlessTracker, config: RefineConfig, bg_config: BackgroundConfig, start: int = 0,
        stop: int | None = None, batch: int = 4, device: torch.device | str | None = None, logger=None,
        log_every: int = 10, progress: bool = True,
        on_pass: Callable[[int, Poses], None] | None = None, workers: int | ObservationWorker = 0,
        sequence: MovingSequence | None = None) -> tuple[Poses, float, BackgroundModel]:
    """Track, then up to ``config.passes`` times re-estimate the background from the track and track again; with
    ``keep: fit`` the passes stop ``config.patience`` passes after the best-fitting settled one, with ``keep: last`` and
    ``config.min_change_m`` the pass after the first whose track moved less than that from the one before
    (:func:`track_change_m`), and tracked as many frames, is the last. On a sequence faster than
    ``config.max_fps`` the passes track every n-th frame (:meth:`RefineConfig.frame_step`) and the result is
    the kept pass's background tracked at the full rate.

    A tracker given its initial pose starts every pass from it; one that was not (the automatic start) is reset
    before each pass and searches for its start on that pass's observation (:meth:`MarkerlessTracker.reset`), so
    that a wrong start on the first, poorest background is not carried through the passes. The background is
    re-estimated from ``bg_config.max_frames`` evenly spaced frames of ``[start, stop)``, read once with the
    background's passes 1-3 on them done once (:class:`~torchtrack.background.MovingSequence`; the first
    background may come from the whole clip). A frame a pass lost
    is drawn at the pose the tracker held for it; leaving such frames out of every pixel's estimate instead
    was worse on the Pose2Sim demo (docs/results.md, "Tried and dropped"). Frames never tracked (before the
    first initialisation) are left out. A first pass that tracks no frame ends the refinement with a warning and
    its poses.

    The result is the track of the pass ``config.keep`` names: the refined pass that fits its observation best
    (``fit``; its number in ``extra['refinement_pass']``, 1 the first pass), or the last one. The logger gets
    the result's track: with ``fit`` that pass is tracked once more at the end, started as it was, on the
    same background (the tracker is deterministic on a CPU: the same track; on CUDA, whose scatter-adds are not,
    a track that differs is warned about), with the logger, and so that the tracker
    ends in that track's state (also without a logger, where the kept pass is not the last); with ``last`` (or
    no refinement) the last pass is logged as it runs.

    Args:
        background: the background of the first pass. make_observer: builds an observer on a background.
        on_pass: called with the pass number (0 first) and its poses after each track, the logged one too.
        sequence: the frames the first background was estimated from, with its passes 1-3
            (:meth:`BackgroundModel.from_folder_and_frames`): used, not read and estimated again, when they are
            the frames the refinement samples, at its size and settings.
        Others: as :func:`~torchtrack.tracking.run.track_sequence`.

    Returns:
        the kept pass's poses, the seconds all passes took (reading, refinement and tracking), and its
        background.

    Raises:
        InputError: refinement asked for with fewer than ``MIN_SEQUENCE_FRAMES`` frames in ``[start, stop)``.
    """
    t0 = time.perf_counter()
    stop = folder.num_frames if stop is None else min(stop, folder.num_frames)
    if config.passes and stop - start < MIN_SEQUENCE_FRAMES:
        raise InputError(f"{folder.root}: background refinement needs at least {MIN_SEQUENCE_FRAMES} frames, "
                         f"[{start}, {stop}) has {max(stop - start, 0)} (set background_refinement.passes to 0)")
    # a given start is kept by every pass; an automatic one is searched for again on each pass's observation
    searched = not tracker.initialized
    start_state = None if searched else (tracker.angles.clone(), tracker.subject.skeleton, tracker.floor_z)
    observer = make_observer(background)
    rig = observer.rig
    W, H = (int(v) for v in rig.image_size_wh[0].tolist())
    tiles = PixelTiles(rig) if config.passes else None  # the pixel rays of every pass's body masks
    indices, frames, poses = None, None, None
    final = config.passes  # the last pass: all of them, or the one after convergence
    select = config.keep == "fit" and config.passes > 0
    step = config.frame_step(folder.fps) if config.passes else 1  # the passes' frames; the result at the full rate
    if step > 1:
        log.info("background refinement: the passes track every %d%s frame (max_fps %g)", step,
                 {2: "nd", 3: "rd"}.get(step, "th"), config.max_fps)
    best: tuple[tuple[int, float], int, Poses, BackgroundModel] | None = None  # (rank, pass, track, background)
    settled: tuple[tuple[int, float], int, Poses, BackgroundModel] | None = None  # the same of settled passes
    for p in range(config.passes + 1):
        last = p == final
        if p > 0:
            if not poses.valid.any():
                warnings.warn(f"{folder.root}: pass {p} tracked no frame; the background is not refined "
                              f"{'' if p == 1 else 'further '}from it",
                              DataWarning, stacklevel=2)
                break
            if frames is None:  # read once, and the background's passes 1-3 on them done once
                indices = [start + i for i in evenly_spaced(stop - start, bg_config.max_frames)]
                if (sequence is not None and sequence.indices == indices and sequence.config == bg_config
                        and sequence.shape[-2:] == (H, W)):
                    frames = sequence
                else:
                    indices, frames = folder.sample_frames(bg_config.max_frames, start, stop, device=device,
                                                           size_wh=(W, H),
                                                           progress="background refinement" if progress else None)
                    frames = MovingSequence(frames, bg_config, folder.camera_names, indices=indices)
                sequence = None  # in use as frames, or not of use
            # each sampled frame at the pose of the nearest frame the pass tracked (a lost frame: the pose the
            # tracker held for it)
            k = np.abs(np.asarray(indices)[:, None] - poses.frame_index[None]).argmin(1)
            angles = torch.as_tensor(poses.angles[k])
            if p == 1 and start_state is not None and tracker.body_version:
                # the first pass moved the given start's hips (TrackerConfig.functional_hips): start in that body
                start_state = (tracker.restate(start_state[0][None], 0)[0], tracker.subject.skeleton, start_state[2])
            background = refined_background(frames, angles, rig, tracker.subject.skeleton, bg_config, config,
                                            folder.camera_names, tracker.subject.blobs, tiles)
            observer = make_observer(background)
            restart(tracker, start_state)
            log.info("background refinement: pass %d of %d", p + 1, config.passes + 1)
        before = poses
        # with the selection or a frame step the logs come from the chosen pass, tracked once more at the end
        poses, _ = track_sequence(folder, observer, tracker, start, stop, batch, device,
                                  logger=logger if last and not select and step == 1 else None,
                                  log_every=log_every, progress=progress,
                                  desc=f"track {p + 1}/{config.passes + 1}" if config.passes else "track",
                                  workers=workers, step=step)
        ran = p
        if on_pass is not None:
            on_pass(p, poses)
        if select and p > 0:
            res = mean_ik_residual_m(poses)  # NaN: no valid frame
            rank = (int((~poses.valid).sum()), res if np.isfinite(res) else float("inf"))
            change = track_change_m(poses, before)
            log.info("background refinement: pass %d moved the track %.1f mm, mean IK residual %.1f mm", p + 1,
                     1e3 * change, 1e3 * res)
            if best is None or rank < best[0]:
                best = (rank, p, poses, background)
            # the residuals of passes whose backgrounds still move compare fits to different observations: only
            # settled passes compete, once there are any
            if change < config.min_change_m and (settled is None or rank < settled[0]):
                settled = (rank, p, poses, background)
        if last:
            break
        if select and settled is not None and p >= settled[1] + config.patience:  # patience passes without a
            break  # better settled fit
        if not select and p > 0 and config.min_change_m > 0:
            change = track_change_m(poses, before)
            log.info("background refinement: pass %d moved the track %.1f mm", p + 1, 1e3 * change)
            # settled: it moved little where both passes tracked, and lost no frame the pass before tracked
            if change < config.min_change_m and int(poses.valid.sum()) >= int(before.valid.sum()):
                # one more pass, on the newest background, is the last
                final = p + 1
                log.info("background refinement: converged; pass %d is the last", p + 2)
    best = settled if settled is not None else best
    chosen = ran
    if best is not None:
        _, chosen, poses, background = best
        log.info("background refinement: pass %d fits its observation best (mean IK residual %.1f mm)",
                 chosen + 1, 1e3 * best[0][1])
    # tracked once more: at the full rate after passes with a frame step; else with the selection when the chosen
    # pass is not the last (so that the tracker ends in its state: its body, if a later pass moved the hips) or
    # for its logs. The same start and background, so at the same rate the same track
    if step > 1 or (best is not None and (logger is not None or chosen != ran)):
        observer = make_observer(background)
        restart(tracker, start_state)
        kept = poses
        poses, _ = track_sequence(folder, observer, tracker, start, stop, batch, device, logger=logger,
                                  log_every=log_every, progress=progress,
                                  desc=f"pass {chosen + 1} again" + (" (every frame)" if step > 1 else ""),
                                  workers=workers)
        if step == 1:
            lost, moved = int((~poses.valid).sum()), track_change_m(poses, kept)
            if lost != int((~kept.valid).sum()) or moved > 1e-3:
                log.warning("background refinement: pass %d tracked again differs from its first track (%d lost "
                            "frames, moved %.1f mm; a non-deterministic device?)", chosen + 1, lost, 1e3 * moved)
        if on_pass is not None:
            on_pass(ran + 1, poses)
    if best is not None:
        poses.extra["refinement_pass"] = np.int64(chosen + 1)
    return poses, time.perf_counter() - t0, background
