"""Marker-based tracking of a folder with ``calibration.toml`` and ``markers2d.npz`` (``torchtrack track --mode
markers``): the subject from the first frames' triangulated markers, then the annealed particle filter frame by
frame (:class:`~torchtrack.tracking.particles.MarkerAPF`)."""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchtrack.cameras import load_calibration
from torchtrack.checks import InputError
from torchtrack.io.markers2d import load_markers2d
from torchtrack.io.poses import Poses
from torchtrack.logging import RunLogger
from torchtrack.markers.model import fit_poses_to_markers, subject_from_markers
from torchtrack.markers.triangulate import triangulate_candidates
from torchtrack.tracking.particles import APFConfig, MarkerAPF, pinhole_pixels, projection_matrices

__all__ = ["MarkerTrack", "is_marker_folder", "track_markers"]

log = logging.getLogger(__name__)

#: The subject (bone lengths, marker offsets) is fitted on the triangulated markers of this many first seconds.
FIT_SECONDS = 2.0
#: ... or, where those do not place every joint centre (markers hidden from all but one camera), up to this many.
MAX_FIT_SECONDS = 10.0
#: The track is lost where more than LOST_SHARE of the markers two views triangulate (at least LOST_MIN_MARKERS)
#: lie farther than LOST_M from the estimate's: a few markers off is a limb's error, most of them the body's.
LOST_M, LOST_SHARE, LOST_MIN_MARKERS = 0.1, 0.3, 6
#: A frame with fewer markers detected in any view is not tracked (marked invalid; the filter holds its state).
MIN_DETECTED = 3


def is_marker_folder(folder: str | Path) -> bool:
    """A folder for marker mode: ``markers2d.npz`` and no video (``video/`` or ``frames/``)."""
    folder = Path(folder)
    return (folder / "markers2d.npz").is_file() and not (folder / "video").exists() and not (
        folder / "frames").exists()


@dataclass(frozen=True)
class MarkerTrack:
    """A marker track: the poses (with ``marker_names`` and ``markers3d``; ``extra``: ``particle_spread_m (T,)``)
    and the wall-clock seconds it took."""

    poses: Poses
    seconds: float


def track_markers(folder: str | Path, config: APFConfig = APFConfig(), start: int = 0, stop: int | None = None,
                  seed: int = 0, progress: bool = True, logger: RunLogger | None = None,
                  log_every: int = 10) -> MarkerTrack:
    """Track the markers of ``folder`` (``calibration.toml``, ``markers2d.npz``) over frames ``[start, stop)``.

    ``logger``: TensorBoard scalars for every frame and, every ``log_every`` frames, each camera's picture of the
    detections and the model's markers (:func:`_log_frame`).

    Raises:
        InputError: a missing or malformed file (named), cameras of the detections missing from the calibration,
            too few frames, or first frames whose markers do not give the joint centres.
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    folder = Path(folder)
    calib = folder / "calibration.toml"
    if not calib.is_file():
        raise InputError(f"{folder}: no calibration.toml")
    rig = load_calibration(calib, warn_units=False).double()
    det = load_markers2d(folder / "markers2d.npz")
    missing = [n for n in det.camera_names if n not in rig.names]
    if missing:
        raise InputError(f"{folder / 'markers2d.npz'}: cameras {missing} are not in {calib} ({rig.names})")
    rig = rig.subset(det.camera_names)  # the detections' camera order
    T_all = len(det.frame_index)
    stop = T_all if stop is None else min(int(stop), T_all)
    if not 0 <= start < stop:
        raise InputError(f"{folder}: frames [{start}, {stop}) hold nothing to track ({T_all} frames)")
    uv = torch.from_numpy(det.uv[start:stop].astype(np.float64))  # (T, C, M, K, 2)
    z = pinhole_pixels(rig, uv.permute(1, 0, 2, 3, 4)).permute(1, 0, 2, 3, 4)
    T, _, M = z.shape[:3]
    P = projection_matrices(rig)
    X_all, _ = triangulate_candidates(z, P)  # (T, M, 3): the subject's fit and the lost-track test
    # the subject from the first seconds; where their markers do not give every joint centre, from more of them
    for seconds in (FIT_SECONDS, MAX_FIT_SECONDS):
        n_fit = min(T, max(2, round(seconds * det.fps)))
        X = X_all[:n_fit]
        enough = torch.isfinite(X).all(-1).sum(0) >= 2  # (M,)
        keep = enough.nonzero()[:, 0]
        names = [det.marker_names[i] for i in keep.tolist()]
        try:
            if len(names) < 3:
                raise InputError(f"{folder}: fewer than 3 markers are seen by two cameras in the first {n_fit} "
                                 "frames")
            skel, mset, angles = subject_from_markers(X[:, keep], names, det.fps,
                                                      source=f"{folder}, the first {n_fit} frames' markers")
            break
        except InputError:
            if n_fit == T or seconds == MAX_FIT_SECONDS:
                raise
    if not bool(enough.all()):
        log.warning("%s: markers %s are seen by two cameras in fewer than 2 of the first %d frames: not tracked",
                    folder, [n for n, ok in zip(det.marker_names, enough.tolist()) if not ok], n_fit)
    log.info("%s: subject fitted on %d frames: %d markers, %.2f m tall", folder, n_fit, len(names), skel.height())
    apf = MarkerAPF(skel, mset, rig, config, torch.Generator().manual_seed(int(seed)))
    apf.reset(angles[0])
    zk, Xk = z[:, :, keep], X_all[:, keep]
    states, spread, restarted, valid = [], [], [], []
    detected = torch.isfinite(zk).all(-1).any(-1).any(1).sum(-1)  # (T,) markers found in some view
    bar = tqdm(range(T), desc=f"track markers {folder.name}", unit="frame", disable=not progress)
    with contextlib.ExitStack() as closing:
        video = None  # the folder's video for the logged pictures: opened at the first, decoded forwards from then
        for t in bar:
            step = int(det.frame_index[start + t])
            if int(detected[t]) < MIN_DETECTED:  # nothing to weigh the particles by: held, marked invalid
                if logger is not None:
                    logger.scalars(step, markers__detected=int(detected[t]), markers__restarts=sum(restarted))
                apf.hold()
                states.append(apf.state.clone())
                spread.append(math.nan)
                restarted.append(False)
                valid.append(False)
                continue
            est = apf.step(zk[t])
            again = _lost(apf, est, Xk[t])
            if again:  # the filter lost the body: start it again from this frame's triangulated markers
                est = _restart(apf, est, Xk[t], angles[0])
                apf.reset(est)
            states.append(est)
            spread.append(apf.spread)
            restarted.append(again)
            valid.append(True)
            bar.set_postfix(restarts=sum(restarted))
            if logger is not None:
                model = apf.markers(est[None])[0]
                seen = torch.isfinite(Xk[t]).all(-1)
                err = (model - Xk[t]).norm(dim=-1)[seen].mean() if bool(seen.any()) else torch.tensor(math.nan)
                logger.scalars(step, markers__detected=int(detected[t]), markers__particle_spread_mm=1e3 * apf.spread,
                               markers__restarts=sum(restarted), markers__triangulated_error_mm=1e3 * float(err))
                if t % max(1, log_every) == 0:
                    if video is None and ((folder / "video").is_dir() or (folder / "frames").is_dir()):
                        from torchtrack.io.sequence import SequenceFolder

                        video = closing.enter_context(SequenceFolder(folder, rig))
                    _log_frame(logger, step, video, rig, det.uv[start + t], model, Xk[t],
                               skel.landmarks(est[None])[0])
    A = torch.stack(states)
    with torch.no_grad():
        fk = skel.forward(A)
        tracked = mset.positions(fk.bone_frames)
    markers3d = torch.full((T, M, 3), math.nan, dtype=torch.float64)
    markers3d[:, keep] = tracked
    poses = Poses(fps=det.fps, frame_index=np.asarray(det.frame_index[start:stop]),
                  joint_names=list(skel.output_names), joints3d=fk.output_points.float().numpy(),
                  dof_names=list(skel.dof_names), angles=A.float().numpy(), valid=np.asarray(valid, dtype=bool),
                  confidence=np.ones((T, len(skel.output_names)), dtype=np.float32),
                  marker_names=list(det.marker_names), markers3d=markers3d.float().numpy(),
                  extra={"particle_spread_m": np.asarray(spread, dtype=np.float32),
                         "reinitialised": np.asarray(restarted, dtype=bool)})
    return MarkerTrack(poses, time.perf_counter() - t0)


def _log_frame(logger: RunLogger, step: int, video, rig, uv: np.ndarray, model: torch.Tensor,
               triangulated: torch.Tensor, landmarks: torch.Tensor) -> None:
    """One frame's pictures: per camera (``cameras/markers/<name>``) the frame of ``video`` (an open
    :class:`~torchtrack.io.sequence.SequenceFolder`; None: a black canvas) with the detections, the model's markers
    and the skeleton (:func:`~torchtrack.tracking.draw.draw_marker_overlays`); and a 3D cloud (``pose/markers``) of
    the triangulated markers (grey), the model's (green) and the skeleton."""
    from torchtrack.tracking.draw import MARKER_RGB, VOXEL_RGB, draw_marker_overlays

    for c, name in enumerate(rig.names):
        w, h = (int(v) for v in rig.image_size_wh[c].tolist())
        image = torch.zeros(1, 3, h, w)
        if video is not None and step < video.num_frames:
            frame, ok = video.read_camera_frames(c, [step])
            if ok[0]:
                image = torch.from_numpy(frame[0]).permute(2, 0, 1)[None].float() / 255.0
        det = torch.from_numpy(uv[c].reshape(1, -1, 2).astype(np.float64))
        out = draw_marker_overlays(image, rig.subset([name]), model, det, landmarks)
        logger.camera_images(step, "cameras/markers", out, [name])
    seen = torch.isfinite(triangulated).all(-1)
    points = torch.cat([triangulated[seen], model])
    colours = torch.cat([points.new_tensor(VOXEL_RGB).expand(int(seen.sum()), 3),
                         points.new_tensor(MARKER_RGB).expand(model.shape[0], 3)])
    logger.pose_cloud(step, "pose/markers", points, landmarks, colours)


def _lost(apf: MarkerAPF, angles: torch.Tensor, X: torch.Tensor) -> bool:
    """Whether the estimate ``angles (D,)`` has lost the body: more than ``LOST_SHARE`` of the markers that two
    views triangulate this frame (``X (M, 3)``, NaN where not; at least ``LOST_MIN_MARKERS``) lie farther than
    ``LOST_M`` from the estimate's. The particles' spread, the paper's test, barely grows when the whole cloud
    follows a wrong pose (docs/results.md, "Marker-based capture")."""
    seen = torch.isfinite(X).all(-1)
    if int(seen.sum()) < LOST_MIN_MARKERS:
        return False
    d = (apf.markers(angles[None])[0][seen] - X[seen]).norm(dim=-1)
    return float((d > LOST_M).double().mean()) > LOST_SHARE


def _restart(apf: MarkerAPF, angles: torch.Tensor, X: torch.Tensor, first: torch.Tensor) -> torch.Tensor:
    """The pose whose markers best fit the triangulated ``X (M, 3)``: inverse kinematics from the lost estimate and
    from the first frame's pose moved onto the markers at four headings, all at once; the least error kept."""
    seen = torch.isfinite(X).all(-1)
    centre = X[seen].mean(0)
    starts = [angles.double()]
    for k in range(4):
        a = first.double().clone()
        a[:2] = centre[:2]
        a[3] = first[3] + k * math.pi / 2
        starts.append(a)
    S = torch.stack(starts)
    fit = fit_poses_to_markers(apf.skeleton, apf.marker_set, S, X[None].expand(S.shape[0], -1, -1))
    err = (apf.markers(fit) - X).norm(dim=-1)[:, seen].mean(-1)
    return fit[int(err.argmin())]
