"""Tracking a whole sequence folder: read, observe, track, log; the loop behind `torchtrack track`."""

from __future__ import annotations

import logging
import time
from contextlib import closing

import numpy as np
import torch

from torchtrack.checks import InputError
from torchtrack.io.poses import Poses
from torchtrack.io.sequence import SequenceFolder, min_readable_cameras
from torchtrack.tracking.markerless import MarkerlessTracker
from torchtrack.tracking.observation import Observer
from torchtrack.tracking.stream import observe_batches

log = logging.getLogger(__name__)


def track_sequence(folder: SequenceFolder, observer: Observer, tracker: MarkerlessTracker, start: int = 0,
                   stop: int | None = None, batch: int = 4, device: torch.device | str | None = None,
                   logger=None, log_every: int = 10, progress: bool = True, desc: str = "track",
                   workers: int = 0) -> tuple[Poses, float]:
    """Track frames ``[start, stop)`` of ``folder``.

    A frame is tracked from the cameras whose frame is readable (a camera that ends early or stops decoding is
    left out of the frames it lacks: the occupancy takes no evidence from it), when at least
    :func:`~torchtrack.io.sequence.min_readable_cameras` are; with fewer it is not tracked and comes out
    ``valid = False``, as does a frame with nobody in the volume. Cameras left out are named in one warning per
    camera and in ``extra['cameras_valid']``. Errors of the tracker name the frame.

    Args:
        folder: the sequence. observer: the observation model at the processing size (its rig's size is the
            size frames are read at). tracker: a fresh or initialised :class:`MarkerlessTracker`.
        logger: a :class:`~torchtrack.logging.RunLogger` or None; it gets per-frame scalars and, every
            ``log_every`` frames, every camera's image with the pose drawn and the voxels with the skeleton (the
            voxels EM fitted: merged per cell with the tracker's ``em_cell_m``).
        desc: the progress bar's label.
        workers: 1 reads and observes the frames in a worker process, ahead of the tracker (CPU; it starts in
            2-3 s, and a calling script needs an ``if __name__ == "__main__":`` guard; see
            :func:`~torchtrack.tracking.stream.observe_batches`); 0 in this process.

    Returns:
        the poses (docs/formats.md; ``extra`` holds ``subject_height_m``, ``observation_model``,
        ``ik_residual_m``, ``explained``, ``reinitialised``, ``camera_names`` and ``cameras_valid`` (T, C), and
        ``body_urdf``, the subject's fitted body as URDF text, once initialised) and the seconds taken.
    """
    from tqdm import tqdm

    rig = observer.rig
    stop = folder.num_frames if stop is None else min(stop, folder.num_frames)
    if stop <= start:
        raise InputError(f"{folder.root}: no frames in [{start}, {stop}) ({folder.num_frames} frames)")
    tracker.set_frame_rate(folder.fps)
    names = tracker.generic.output_names
    T, D = stop - start, tracker.generic.num_dofs
    joints3d = np.full((T, len(names), 3), np.nan, np.float32)
    angles = np.full((T, D), np.nan, np.float32)
    valid = np.zeros(T, bool)
    confidence = np.zeros((T, len(names)), np.float32)
    residual = np.full(T, np.nan, np.float32)
    explained = np.zeros(T, np.float32)
    reinit = np.zeros(T, bool)
    version = np.zeros(T, np.int64)  # the tracker's body_version each frame was tracked in
    cameras_valid = np.zeros((T, len(rig.names)), bool)
    need = min_readable_cameras(len(rig.names))

    def record(k: int, res) -> None:
        joints3d[k] = res.output_points.cpu().numpy()
        angles[k] = res.angles.cpu().numpy()
        valid[k] = res.valid
        confidence[k] = res.confidence.cpu().numpy() if res.valid else 0.0
        residual[k] = res.residual_m
        explained[k] = res.explained
        reinit[k] = res.reinitialised

    t_start = time.perf_counter()
    keep = log_every if logger is not None else 0
    stream = observe_batches(folder, observer, start, stop, batch, device, keep, workers,
                             cell_m=tracker.config.em_cell_m)
    # closing: a tracking error (its traceback holds this frame) must not keep the worker and thread share
    with tqdm(total=T, unit="frame", desc=desc, disable=not progress) as bar, closing(stream):
        while True:
            t0 = time.perf_counter()
            fb = next(stream, None)
            if fb is None:
                break
            observations = fb.observations
            t_obs = fb.seconds / len(observations)
            # per frame, its share of the time the batch took to come (reading and observing it, or waiting
            # for the worker that did) plus its own tracking: the wall-clock rate
            t_wait = (time.perf_counter() - t0) / len(observations)
            for i, obs in enumerate(observations):
                t1 = time.perf_counter()
                t = int(fb.frame_index[i])
                k = t - start
                version[k] = tracker.body_version
                cameras_valid[k] = fb.valid[i].cpu().numpy()
                if cameras_valid[k].sum() < need:  # too few readable cameras to carve the body: not tracked
                    res = tracker.skip()
                else:
                    try:
                        res = tracker.step(obs)
                    except InputError as exc:
                        raise InputError(f"{folder.root}, frame {t}: {exc}") from None
                    except Exception as exc:  # numerical or device errors: say where
                        exc.add_note(f"while tracking {folder.root}, frame {t}")
                        raise
                record(k, res)
                revised = tracker.take_revised()  # a start race won by the start turned round: its frames
                for j, (r, v) in enumerate(revised):
                    record(k - len(revised) + 1 + j, r)
                    version[k - len(revised) + 1 + j] = v
                dt = t_wait + time.perf_counter() - t1
                if logger is not None:
                    _log_frame(logger, t, obs, res, fb.images[i], rig, dt, t_obs)
                bar.update(1)
                bar.set_postfix(valid=f"{valid[:k + 1].mean():.0%}", res_mm=f"{1e3 * res.residual_m:.0f}")
    restate(tracker, angles, joints3d, version)
    _report_cameras(folder, list(rig.names), cameras_valid, start, need)
    _report_start(folder, tracker, reinit, start)
    elapsed = time.perf_counter() - t_start
    extra = {"subject_height_m": np.float64(tracker.height_m or np.nan),
             "observation_model": np.asarray(observer.model), "ik_residual_m": residual, "explained": explained,
             "reinitialised": reinit, "camera_names": np.asarray(list(rig.names)), "cameras_valid": cameras_valid}
    if tracker.subject is not None:  # the subject's body, for a later --init-pose (de Bem's reusable start)
        extra["body_urdf"] = np.asarray(tracker.subject.skeleton.urdf_text)
    poses = Poses(fps=folder.fps, frame_index=np.arange(start, stop, dtype=np.int64), joint_names=list(names),
                  joints3d=joints3d, dof_names=list(tracker.generic.dof_names), angles=angles, valid=valid,
                  confidence=confidence, extra=extra)
    return poses, elapsed


def _report_start(folder: SequenceFolder, tracker: MarkerlessTracker, reinit: np.ndarray, start: int) -> None:
    """Warn once per folder when the start was refused on frames (they are invalid), saying why."""
    refused = tracker.start_refusals
    if not refused or "start" in folder.reported:
        return
    folder.reported.add("start")
    started = np.flatnonzero(reinit)
    where = f"started at frame {start + int(started[0])}" if started.size else "never started"
    log.warning("%s: %s; %d earlier frame(s) with voxels were not started from (invalid), the first because: %s",
                folder.root, where, len(refused), refused[0])


def _report_cameras(folder: SequenceFolder, names: list[str], cameras_valid: np.ndarray, start: int,
                    need: int) -> None:
    """Warn once per folder and camera about the frames it was left out of, and about the frames that had too
    few readable cameras to be tracked (the refinement and refit passes read the same frames again)."""
    from torchtrack.io.video import frame_ranges

    reported = folder.reported
    for c, name in enumerate(names):
        missing = np.flatnonzero(~cameras_valid[:, c])
        if missing.size and f"camera {name}" not in reported:
            reported.add(f"camera {name}")
            log.warning("%s: camera '%s' has no readable frame for %d frame(s) (%s); they were tracked from the "
                        "other cameras where at least %d were readable", folder.root, name, missing.size,
                        frame_ranges((missing + start).tolist()), need)
    few = np.flatnonzero(cameras_valid.sum(1) < need)
    if few.size and "few cameras" not in reported:
        reported.add("few cameras")
        log.warning("%s: %d frame(s) (%s) have fewer than %d readable cameras and were not tracked", folder.root,
                    few.size, frame_ranges((few + start).tolist()), need)


def restate(tracker: MarkerlessTracker, angles: np.ndarray, joints3d: np.ndarray, version: np.ndarray) -> None:
    """In place: the frames tracked in an earlier version of the subject's body (``version (T,)``, the tracker's
    :attr:`~MarkerlessTracker.body_version` then) re-stated in its final body (``functional_hips``;
    :meth:`~MarkerlessTracker.restate`), their output points the final body's at the re-stated angles: the trunk,
    arms and head as tracked, the pelvis and hips raised, the knees and feet as the longer thighs reach them
    (where a thigh is flexed, up to dz (1 - cos flexion) from the tracked ones; keeping the tracked knees, ankles
    and toes instead, which leaves the angles off them, measured no better: docs/results.md, "Tried and dropped")."""
    redo = (version < tracker.body_version) & np.isfinite(angles).all(1)
    if tracker.subject is None or not redo.any():
        return
    skel = tracker.subject.skeleton
    dev = skel.lower.device
    a = tracker.restate(torch.from_numpy(angles[redo]).to(dev, skel.lower.dtype),
                        torch.from_numpy(version[redo]).to(dev))
    angles[redo] = a.cpu().numpy()
    joints3d[redo] = skel.forward(a).output_points.cpu().numpy()


def _log_frame(tb, t: int, obs, res, images: torch.Tensor | None, rig, dt: float, t_obs: float) -> None:
    """Per-frame scalars (``dt``: the frame's wall-clock seconds; ``t_obs``: its observation's); on the frames
    whose ``images`` were kept (every ``log_every``), the drawings."""
    from torchtrack.tracking.draw import draw_pose_overlays

    tb.scalars(t, voxels=float(obs.num_observed), ik_residual_mm=1e3 * res.residual_m, explained=res.explained,
               valid=float(res.valid), fps=1.0 / max(dt, 1e-9), observation_ms=1e3 * t_obs)
    if images is None or not res.valid:
        return
    lm = res.output_points[:16]
    cen = R = semi = None
    if res.blobs is not None:
        evals, evecs = torch.linalg.eigh(res.blobs.cov)
        cen, R, semi = res.blobs.mean, evecs, (5.0 * evals.clamp(min=0)).sqrt()
    img = torch.nan_to_num(images, nan=0.0)
    tb.camera_images(t, "cameras/pose", draw_pose_overlays(img, rig, lm, cen, R, semi), rig.names)
    tb.pose_cloud(t, "pose/voxels_skeleton", obs.points, lm)
