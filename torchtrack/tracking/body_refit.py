"""The body refitted on the track: refit the bone lengths on several tracked frames at once, track again, keep it
while the track fits better.

The automatic initialisation fits the subject's bones to one frame, the starfish pose, whose straight joints
hide where they are: the pelvis' and the thighs' ellipsoids look much the same with the hips a few centimetres
lower and the legs shorter. A first track gives poses where the joints bend. :func:`track_with_body_refit`
then, pass after pass:

1. picks ``frames`` of the track's valid frames, evenly spaced, and refits the bone lengths on all of them at
   their tracked poses (:meth:`MarkerlessTracker.refit_bone_lengths`: the bone groups' scales and the neck's
   height shared, a root shift per frame);
2. tracks the sequence again from the track's first valid pose with that body;
3. keeps the new track when its mean IK residual (the goals' mean distance to the solved joints, a measure of
   how well the skeleton explains the blobs that needs no ground truth) is at least ``min_gain`` lower than
   the kept one's and it lost no frame the kept one tracked; otherwise the kept track and body stay and the
   passes stop (the next refit would start from the same body and end where this one did).

The residual mostly follows the error on the synthetic sequences, not always (docs/results.md, "Tracker
settings").
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np
import torch

from torchtrack.checks import InputError, config_section
from torchtrack.io.poses import Poses
from torchtrack.io.sequence import SequenceFolder, evenly_spaced
from torchtrack.skeleton import Skeleton
from torchtrack.tracking.markerless import MarkerlessTracker
from torchtrack.tracking.observation import Observer
from torchtrack.tracking.run import track_sequence
from torchtrack.tracking.stream import ObservationWorker

__all__ = ["BodyRefitConfig", "mean_ik_residual_m", "refit_frames", "refit_body_on_track", "track_with_body_refit"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BodyRefitConfig:
    """Body refit settings (the ``body_refit`` section of a tracking config).

    Attributes:
        passes: refits at most, each followed by a new track (0: off).
        frames: how many of the track's valid frames, evenly spaced, each refit uses (at least 2).
        min_gain: a pass is kept when its track's mean IK residual is at least this fraction lower than the kept
            track's (0: any decrease).
        given_body: also refit a body that came with the start (``torchtrack track --init-pose`` of a file with
            a body: an earlier run's, or one fitted to 3D keypoints, which place the hips themselves). Off: on the
            Pose2Sim demo, from the body fitted to its reference keypoints, every pass lowered the residual and
            raised the error (docs/results.md, "Tracker settings").
    """

    passes: int = 3
    frames: int = 8
    min_gain: float = 0.01
    given_body: bool = False

    def __post_init__(self) -> None:
        for name in ("passes", "frames"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise InputError(f"body_refit.{name} must be a whole number, got {value!r}")
        if self.passes < 0:
            raise InputError(f"body_refit.passes must be >= 0 (0: off), got {self.passes}")
        if self.frames < 2:
            raise InputError(f"body_refit.frames must be >= 2 (one frame is what the initialisation fits), got "
                             f"{self.frames}")
        g = self.min_gain
        if isinstance(g, bool) or not isinstance(g, (int, float)) or not 0.0 <= g < 1.0:
            raise InputError(f"body_refit.min_gain must be a number in [0, 1), got {g!r}")
        if not isinstance(self.given_body, bool):
            raise InputError(f"body_refit.given_body must be true or false, got {self.given_body!r}")

    def for_start(self, body_given: bool) -> BodyRefitConfig:
        """These settings for a run whose body came with its start (``body_given``): no passes unless
        ``given_body``."""
        return replace(self, passes=0) if body_given and not self.given_body else self

    @classmethod
    def from_dict(cls, doc: dict[str, Any] | None, source: str = "<config>") -> BodyRefitConfig:
        """Build from the YAML section (None: the defaults), naming unknown keys."""
        return cls(**config_section(cls, doc, source, "body_refit", " (passes: 0 turns it off)"))


def mean_ik_residual_m(poses: Poses) -> float:
    """The mean IK residual (``extra['ik_residual_m']``) over the track's valid frames; NaN without any."""
    res = np.asarray(poses.extra["ik_residual_m"], np.float64)[np.asarray(poses.valid, bool)]
    res = res[np.isfinite(res)]
    return float(res.mean()) if res.size else float("nan")


def refit_frames(poses: Poses, count: int) -> np.ndarray:
    """Indices into ``poses`` of up to ``count`` of its valid frames that the voxels tracked (a finite IK residual:
    not a frame the images held, ``TrackerConfig.image_hold_s``), evenly spaced from the first to the last (sorted,
    distinct)."""
    residual = np.asarray(poses.extra.get("ik_residual_m", np.zeros(len(poses.valid))), np.float64)
    ok = np.flatnonzero(np.asarray(poses.valid, bool) & np.isfinite(residual))
    return ok[evenly_spaced(ok.size, count)] if ok.size else ok


def refit_body_on_track(folder: SequenceFolder, observer: Observer, tracker: MarkerlessTracker, poses: Poses,
                        frames: int, size_wh: tuple[int, int] | None = None,
                        device: torch.device | str | None = None, progress: str | None = None
                        ) -> tuple[Skeleton, float]:
    """The tracker's body refitted on ``frames`` of the track's valid frames (:func:`refit_frames`) at their
    tracked poses, which must be under the tracker's current subject (as :func:`track_sequence` leaves them).

    Args:
        folder: the sequence; ``poses.frame_index`` are its frame numbers. observer: observes the picked
            frames.
        size_wh: the images' size the observer wants (None: the folder's own). device: where the frames are
            decoded to (the observer's). progress: the label of the shape fit's progress bar (None: no bar).

    Returns:
        the refitted skeleton and its largest relative change (:meth:`MarkerlessTracker.refit_bone_lengths`).

    Raises:
        InputError: the track has fewer than 2 valid frames, or a picked frame cannot be read.
    """
    picked = refit_frames(poses, frames)
    if picked.size < 2:
        raise InputError(f"{folder.root}: the body refit needs at least 2 tracked frames, the track has "
                         f"{picked.size}")
    batch = folder.read_frames(np.asarray(poses.frame_index)[picked].tolist(), device=device, size_wh=size_wh)
    unread = batch.frame_index[~batch.valid.any(dim=1)].tolist()
    if unread:
        raise InputError(f"{folder.root}: frames {unread}, tracked before, cannot be read for the body refit")
    observations = observer(batch.images, batch.valid)  # the picked frames observed as one batch
    angles = torch.as_tensor(np.asarray(poses.angles)[picked], dtype=torch.float32)
    return tracker.refit_bone_lengths(observations, angles, progress=progress)


def track_with_body_refit(
        folder: SequenceFolder, make_observer: Callable[[], Observer], tracker: MarkerlessTracker, poses: Poses,
        config: BodyRefitConfig, start: int = 0, stop: int | None = None, batch: int = 4,
        device: torch.device | str | None = None, make_logger: Callable[[int], Any] | None = None,
        log_every: int = 10,
        progress: bool = True, on_pass: Callable[[int, Poses, bool], None] | None = None,
        workers: int | ObservationWorker = 0) -> tuple[Poses, float]:
    """After a track ``poses`` of ``[start, stop)`` by ``tracker`` (its subject still the one the track ended
    with), up to ``config.passes`` times: refit the body on the kept track (:func:`refit_body_on_track`), track
    again from the kept track's first valid pose with it, and keep the new track if it fits better (see the
    module docstring). The tracker ends with the kept track's body: where a later pass was turned down, it is
    started again from the kept track's first valid pose.

    Args:
        make_observer: a new observer of the frames (called for each pass's refit and track: an observer that
            counts the frames it has seen starts from 0 every time).
        make_logger: gives the logger of pass N's track (a :class:`~torchtrack.logging.RunLogger`, closed here
            after the pass), e.g. TensorBoard in ``log_dir/body_refit_N`` (None: not logged).
        on_pass: called with the pass number (1 first), its track and whether it was kept.
        Others: as :func:`~torchtrack.tracking.run.track_sequence`.

    Returns:
        the kept track and the seconds the passes took (0 without any).
    """
    t0 = time.perf_counter()
    if config.passes == 0 or not tracker.initialized:
        return poses, 0.0
    if int(np.asarray(poses.valid).sum()) < 2:
        log.warning("%s: the body is not refitted: the track has fewer than 2 valid frames", folder.root)
        return poses, 0.0
    floor_z = tracker.floor_z
    kept, kept_body = poses, tracker.subject.skeleton
    kept_res = mean_ik_residual_m(poses)
    for p in range(1, config.passes + 1):
        observer = make_observer()
        size_wh = tuple(int(v) for v in observer.rig.image_size_wh[0].tolist())
        body, change = refit_body_on_track(folder, observer, tracker, kept, config.frames, size_wh, device,
                                           progress=f"body refit {p}/{config.passes}: shape" if progress else None)
        first = int(np.flatnonzero(np.asarray(kept.valid))[0])
        tracker.initialize_from_pose(torch.as_tensor(kept.angles[first]).to(tracker.angles), skeleton=body,
                                     floor_z_m=floor_z)
        log.info("body refit: pass %d of %d (largest change %.1f %%)", p, config.passes, 100 * change)
        logger = make_logger(p) if make_logger is not None else None
        try:
            new, _ = track_sequence(folder, make_observer(), tracker, start, stop, batch, device, logger=logger,
                                    log_every=log_every, progress=progress, desc=f"body refit {p}/{config.passes}",
                                    workers=workers)
        finally:
            if logger is not None:
                logger.close()
        res = mean_ik_residual_m(new)
        lost = np.asarray(kept.valid, bool) & ~np.asarray(new.valid, bool)  # frames the kept track had
        better = res <= (1.0 - config.min_gain) * kept_res and not lost.any()
        log.info("body refit: pass %d IK residual %.1f mm against %.1f kept: %s", p, 1e3 * res, 1e3 * kept_res,
                 "kept" if better else "turned down")
        if on_pass is not None:
            on_pass(p, new, better)
        if not better:
            break
        kept, kept_body, kept_res = new, tracker.subject.skeleton, res
    first = int(np.flatnonzero(np.asarray(kept.valid))[0])
    if tracker.subject.skeleton is not kept_body:
        tracker.initialize_from_pose(torch.as_tensor(kept.angles[first]).to(tracker.angles), skeleton=kept_body,
                                     floor_z_m=floor_z)
    return kept, time.perf_counter() - t0
