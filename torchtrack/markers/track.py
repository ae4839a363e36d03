"""Marker-based tracking of a folder with ``calibration.toml`` and ``markers2d.npz`` (``torchtrack track --mode
markers``): the subject from the first frames' triangulated markers, then the annealed particle filter frame by
frame (:class:`~torchtrack.tracking.particles.MarkerAPF`)."""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from torchtrack.cameras import CameraRig, load_calibration
from torchtrack.checks import InputError
from torchtrack.io.markers2d import Markers2D, load_markers2d
from torchtrack.io.poses import Poses
from torchtrack.logging import RunLogger
from torchtrack.markers.gaps import BODY, NONE, measured_markers
from torchtrack.markers.model import MarkerSet, fit_marker_set, fit_poses_to_markers, subject_from_markers
from torchtrack.markers.triangulate import triangulate_candidates
from torchtrack.skeleton.model import Skeleton
from torchtrack.tracking.epipolar import pinhole_pixels, projection_matrices
from torchtrack.tracking.particles import LIMBS, APFConfig, MarkerAPF

__all__ = ["MarkerSequence", "MarkerTrack", "is_marker_folder", "load_marker_sequence", "track_marker_sequences",
           "track_markers"]

log = logging.getLogger(__name__)

#: The subject (bone lengths, marker offsets) is fitted on the triangulated markers of this many first seconds.
FIT_SECONDS = 2.0
#: ... or, where those do not place every joint centre (markers hidden from all but one camera), up to this many.
MAX_FIT_SECONDS = 10.0
#: The track is lost where more than LOST_SHARE of the markers two views triangulate (at least LOST_MIN_MARKERS)
#: lie farther than LOST_M from the estimate's: a few markers off is a limb's error, most of them the body's; or
#: where their median distance is over LOST_MEDIAN_M: the whole body a few centimetres off, as a filter that half
#: followed a jump is.
LOST_M, LOST_SHARE, LOST_MIN_MARKERS, LOST_MEDIAN_M = 0.1, 0.3, 6, 0.04
#: ... and where more than half of a limb's triangulated markers (at least LOST_LIMB_MARKERS) lie farther than LOST_M:
#: a limb the filter left in another place, which its own markers' resampling does not bring back.
LOST_LIMB_MARKERS = 3
#: A frame with fewer markers detected in any view is not tracked (marked invalid; the filter holds its state).
MIN_DETECTED = 3
#: The marker set's refit (``APFConfig.refit_m``) moves a marker only where this many frames place it, and fits at
#: most this many frames, evenly spread (its inverse kinematics of every frame is a long capture's cost otherwise).
REFIT_MIN_FRAMES, REFIT_MAX_FRAMES = 10, 600


def is_marker_folder(folder: str | Path) -> bool:
    """A folder for marker mode: ``markers2d.npz`` and no video (``video/`` or ``frames/``)."""
    folder = Path(folder)
    return (folder / "markers2d.npz").is_file() and not (folder / "video").exists() and not (
        folder / "frames").exists()


@dataclass(frozen=True)
class MarkerTrack:
    """A marker track: the poses (with ``marker_names`` and ``markers3d``; ``extra``: ``particle_spread_m (T,)``)
    and the wall-clock seconds it took (in lockstep: its loading and subject fit, and the shared track)."""

    poses: Poses
    seconds: float


@dataclass(frozen=True)
class MarkerSequence:
    """A marker folder read and its subject fitted (:func:`load_marker_sequence`): ready to track.

    Attributes:
        folder: the folder. det: its detections. start: the first frame tracked. rig: the cameras, in the
        detections' order. z: (T, C, M, K, 2) the frames' candidates in pinhole pixels. X: (T, M, 3) their
        triangulated markers (NaN where fewer than two views agree). skeleton, marker_set, first: the subject
        and its pose on the first frame. keep: (M',) the markers tracked (those the fit placed). seconds: the
        time the loading and the fit took. views: (T, M) how many views agree on each of ``X`` (None: two
        wherever ``X`` is finite).
    """

    folder: Path
    det: Markers2D
    start: int
    rig: CameraRig
    z: torch.Tensor
    X: torch.Tensor
    skeleton: Skeleton
    marker_set: MarkerSet
    first: torch.Tensor
    keep: torch.Tensor
    seconds: float
    views: torch.Tensor | None = None

    @property
    def num_frames(self) -> int:
        return self.z.shape[0]


def load_marker_sequence(folder: str | Path, start: int = 0, stop: int | None = None) -> MarkerSequence:
    """Read ``folder`` (``calibration.toml``, ``markers2d.npz``) over frames ``[start, stop)`` and fit its subject
    (bone lengths, marker offsets) on the first seconds' triangulated markers.

    Raises:
        InputError: a missing or malformed file (named), cameras of the detections missing from the calibration,
            too few frames, or first frames whose markers do not give the joint centres.
    """
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
    T = z.shape[0]
    # (T, M, 3): the fit, the lost-track test and the output markers
    X_all, views = triangulate_candidates(z, projection_matrices(rig))
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
    return MarkerSequence(folder, det, start, rig, z, X_all, skel, mset, angles[0], keep, time.perf_counter() - t0,
                          views)


def track_markers(folder: str | Path, config: APFConfig = APFConfig(), start: int = 0, stop: int | None = None,
                  seed: int = 0, progress: bool = True, logger: RunLogger | None = None,
                  log_every: int = 10) -> MarkerTrack:
    """Track the markers of ``folder`` (``calibration.toml``, ``markers2d.npz``) over frames ``[start, stop)``:
    :func:`load_marker_sequence`, then :func:`track_marker_sequences` of it alone.

    ``logger``: TensorBoard scalars for every frame and, every ``log_every`` frames, each camera's picture of the
    detections and the model's markers (:func:`_log_frame`).

    Raises:
        InputError: see :func:`load_marker_sequence`.
    """
    result = track_marker_sequences([load_marker_sequence(folder, start, stop)], config, seed, progress,
                                    [logger], log_every)[0]
    if isinstance(result, Exception):
        raise result
    return result


def track_marker_sequences(sequences: Sequence[MarkerSequence], config: APFConfig = APFConfig(), seed: int = 0,
                           progress: bool = True, loggers: Sequence[RunLogger | None] | None = None,
                           log_every: int = 10) -> list[MarkerTrack | Exception]:
    """Track Q loaded sequences in lockstep: one annealed particle filter over all of them
    (:class:`~torchtrack.tracking.particles.MarkerAPF`), each frame one batched step; a sequence that has ended or
    whose frame has too few detections is held (that frame invalid), one that lost its body is started again from
    its triangulated markers alone. With ``config.refit_m``, each subject's marker set is then fitted again along
    its first track (:func:`refit_marker_set`; where that fails, with a warning, the set stays) and the sequences
    tracked again; a sequence whose first track failed is not tracked again. One sequence alone is tracked by the
    same code. Returns each sequence's last track, or the exception its own part (its restart, its refit, its
    TensorBoard pictures) failed with while the others went on.

    Args:
        sequences: from :func:`load_marker_sequence` (subjects of one body chain; any rigs and marker sets).
        config: the filter's settings. seed: each sequence's random draws (a generator of its own: its track is the
            same whichever others it is tracked with).
        loggers: each sequence's TensorBoard logger, or None (see :func:`track_markers`); the last track's.
    """
    t0 = time.perf_counter()
    Q = len(sequences)
    loggers = list(loggers) if loggers is not None else [None] * Q
    if not Q or len(loggers) != Q:
        raise InputError(f"track_marker_sequences: {Q} sequences and {len(loggers)} loggers")
    if not config.refit_m > 0:
        return _track_pass(sequences, config, seed, progress, loggers, log_every, "")
    out = _track_pass(sequences, config, seed, progress, [None] * Q, log_every, " (1 of 2)")
    again, refitted = [], []  # the sequences tracked a second time, each with its refitted marker set
    for q, (s, r) in enumerate(zip(sequences, out)):
        if isinstance(r, Exception):  # its failure stands: a second track would repeat it
            continue
        try:
            s = refit_marker_set(s, r.poses, config.refit_m)
        except Exception as exc:  # this sequence's markers stay as first fitted; the others go on
            log.warning("%s: the marker set was not fitted again along the track (%s): tracked with the first fit",
                        s.folder, exc)
        again.append(q)
        refitted.append(s)
    if again:
        second = _track_pass(refitted, config, seed, progress, [loggers[q] for q in again], log_every, " (2 of 2)")
        for q, r in zip(again, second):
            out[q] = r
    shared = time.perf_counter() - t0
    return [r if isinstance(r, Exception) else replace(r, seconds=s.seconds + shared) for s, r in zip(sequences, out)]


def refit_marker_set(s: MarkerSequence, poses: Poses, within_m: float) -> MarkerSequence:
    """The sequence with its markers' bones and offsets fitted again (:func:`~torchtrack.markers.model.
    fit_marker_set`) on every valid frame's triangulated markers that lie within ``within_m`` of the track
    ``poses``' (a marker placed by fewer than ``REFIT_MIN_FRAMES`` such frames keeps its first fit; at most
    ``REFIT_MAX_FRAMES`` frames); its first pose is the track's (a pose fitted to frame 0's markers alone lets the
    joints that few markers hold drift). Over the first seconds a subject often holds still, which leaves a marker's
    bone and place in it poorly fixed; along a track every joint moves. The gate keeps out detections linked to the
    wrong marker.

    Raises:
        InputError: fewer than 3 markers placed by ``REFIT_MIN_FRAMES`` frames."""
    A = torch.from_numpy(poses.angles).double()
    with torch.no_grad():
        model = s.marker_set.positions(s.skeleton.forward(A).bone_frames)  # (T, M', 3)
    X = s.X[:, s.keep].to(model)
    near = ((X - model).norm(dim=-1) < within_m) & torch.from_numpy(poses.valid)[:, None]
    frames = near.any(1).nonzero()[:, 0]
    if len(frames) > REFIT_MAX_FRAMES:
        frames = frames[torch.linspace(0, len(frames) - 1, REFIT_MAX_FRAMES).round().long()]
    near = near[frames]
    enough = near.sum(0) >= REFIT_MIN_FRAMES  # (M',)
    if int(enough.sum()) < 3:
        raise InputError(f"{s.folder}: fewer than 3 markers lie within {within_m} m of the track on "
                         f"{REFIT_MIN_FRAMES} frames")
    names = [s.marker_set.names[i] for i in enough.nonzero()[:, 0].tolist()]
    target = torch.where(near[..., None], X[frames], math.nan)[:, enough]
    fitted, _ = fit_marker_set(s.skeleton, A[frames], target, names)
    bone, offset = s.marker_set.bone.clone(), s.marker_set.offset.clone()
    bone[enough], offset[enough] = fitted.bone, fitted.offset.to(offset)
    return replace(s, marker_set=MarkerSet(s.marker_set.names, bone, offset), first=A[0].to(s.first))


def _track_pass(sequences: Sequence[MarkerSequence], config: APFConfig, seed: int, progress: bool,
                loggers: list[RunLogger | None], log_every: int, label: str) -> list[MarkerTrack | Exception]:
    """One track of every sequence in lockstep (:func:`track_marker_sequences`); ``label`` for the progress bar."""
    from tqdm import tqdm

    t0 = time.perf_counter()
    Q = len(sequences)
    apf = MarkerAPF([s.skeleton for s in sequences], [s.marker_set for s in sequences], [s.rig for s in sequences],
                    config, [torch.Generator().manual_seed(int(seed)) for _ in sequences])
    apf.reset(torch.stack([s.first.double() for s in sequences]))
    lengths = torch.tensor([s.num_frames for s in sequences])
    Tmax, K = int(lengths.max()), max(s.z.shape[3] for s in sequences)
    # each sequence's markers found in some view, per frame (0 after its end): fewer than MIN_DETECTED, it is held
    detected = torch.zeros(Tmax, Q, dtype=torch.long)
    for q, s in enumerate(sequences):
        detected[:s.num_frames, q] = torch.isfinite(s.z[:, :, s.keep]).all(-1).any(-1).any(1).sum(-1)
    states = torch.empty(Tmax, Q, apf.states.shape[1], dtype=torch.float64)
    spread = torch.full((Tmax, Q), math.nan, dtype=torch.float64)
    restarted = torch.zeros(Tmax, Q, dtype=torch.bool)
    valid = torch.zeros(Tmax, Q, dtype=torch.bool)
    failed: dict[int, Exception] = {}  # a sequence whose restart or logging failed: held from then on, reported
    name = sequences[0].folder.name if Q == 1 else f"{Q} sequences"
    bar = tqdm(range(Tmax), desc=f"track markers {name}{label}", unit="frame", disable=not progress)
    with contextlib.ExitStack() as closing:
        videos: dict[int, object] = {}  # each sequence's video for the logged pictures, opened at the first
        for t in bar:
            active = (t < lengths) & (detected[t] >= MIN_DETECTED)  # nothing to weigh the particles by: held
            for q in failed:
                active[q] = False
            # this frame of each sequence, padded (a frame at a time: the padded copy of whole captures is large)
            Z = apf.pad_detections([s.z[t:t + 1, :, s.keep] for s in sequences], K)[0]  # (Q, C, M, K, 2)
            X = torch.full((Q, Z.shape[2], 3), math.nan, dtype=torch.float64)
            for q, s in enumerate(sequences):
                X[q, :len(s.keep)] = s.X[t, s.keep] if t < s.num_frames else math.nan
            if bool(active.any()):
                est = apf.step_all(Z, active)
                lost = _lost(apf, est, X) & active
                for q in lost.nonzero()[:, 0].tolist():  # the filter lost the body: start it again from the markers
                    try:
                        est[q] = _restart(apf, q, est[q], X[q], sequences[q].first)
                        apf.reset(est[q], subject=q)
                    except Exception as exc:  # this sequence fails; the others go on
                        failed[q] = exc
                restarted[t] = lost
            else:
                apf.hold()
            states[t], valid[t] = apf.states.cpu(), active
            spread[t] = torch.where(active, apf.spreads, math.nan)
            bar.set_postfix(restarts=int(restarted.sum()))
            for q, (s, logger) in enumerate(zip(sequences, loggers)):
                if logger is not None and t < s.num_frames and q not in failed:
                    try:
                        _log_step(logger, apf, s, q, t, states[t, q], X[q, :len(s.keep)], int(detected[t, q]),
                                  bool(active[q]), int(restarted[:t + 1, q].sum()), log_every, videos, closing)
                    except Exception as exc:
                        failed[q] = exc
    shared = time.perf_counter() - t0
    return [failed[q] if q in failed else
            _marker_track(s, states[:s.num_frames, q], spread[:s.num_frames, q], restarted[:s.num_frames, q],
                          valid[:s.num_frames, q], s.seconds + shared, config) for q, s in enumerate(sequences)]


def _log_step(logger: RunLogger, apf: MarkerAPF, s: MarkerSequence, q: int, t: int, est: torch.Tensor,
              X: torch.Tensor, detected: int, tracked: bool, restarts: int, log_every: int, videos: dict,
              closing: contextlib.ExitStack) -> None:
    """Sequence ``q``'s TensorBoard record of frame ``t``: the scalars, and every ``log_every`` frames its
    pictures (:func:`_log_frame`; the sequence's video opened in ``closing`` at the first)."""
    step = int(s.det.frame_index[s.start + t])
    if not tracked:
        logger.scalars(step, markers__detected=detected, markers__restarts=restarts)
        return
    model = apf.markers(est[None], q)[0]
    seen = torch.isfinite(X).all(-1)
    err = (model - X).norm(dim=-1)[seen].mean() if bool(seen.any()) else torch.tensor(math.nan)
    logger.scalars(step, markers__detected=detected, markers__particle_spread_mm=1e3 * float(apf.spreads[q]),
                   markers__restarts=restarts, markers__triangulated_error_mm=1e3 * float(err))
    if t % max(1, log_every) == 0:
        if q not in videos:
            videos[q] = None
            if (s.folder / "video").is_dir() or (s.folder / "frames").is_dir():
                from torchtrack.io.sequence import SequenceFolder

                videos[q] = closing.enter_context(SequenceFolder(s.folder, s.rig))
        _log_frame(logger, step, videos[q], s.rig, s.det.uv[s.start + t], model, X,
                   s.skeleton.landmarks(est[None])[0])


def _marker_track(s: MarkerSequence, A: torch.Tensor, spread: torch.Tensor, restarted: torch.Tensor,
                  valid: torch.Tensor, seconds: float, config: APFConfig) -> MarkerTrack:
    """One sequence's track ``A (T, D)`` as :class:`MarkerTrack`: poses with every marker's position, measured
    where the views show it and filled from the body elsewhere (:func:`~torchtrack.markers.gaps.measured_markers`;
    the body's alone in ``markers3d_body``)."""
    T, M = s.num_frames, len(s.det.marker_names)
    with torch.no_grad():
        fk = s.skeleton.forward(A)
        tracked = s.marker_set.positions(fk.bone_frames)
    body = torch.full((T, M, 3), math.nan, dtype=torch.float64)
    body[:, s.keep] = tracked
    if config.measured_m > 0:
        views = s.views if s.views is not None else torch.isfinite(s.X).all(-1).long() * 2
        markers3d, source = measured_markers(body, s.X.to(body), views, config.measured_views, config.measured_m,
                                             round(config.fill_s * s.det.fps), config.smooth_s * s.det.fps)
    else:
        markers3d = body
        source = torch.where(torch.isfinite(body).all(-1), BODY, NONE).to(torch.uint8)
    poses = Poses(fps=s.det.fps, frame_index=np.asarray(s.det.frame_index[s.start:s.start + T]),
                  joint_names=list(s.skeleton.output_names), joints3d=fk.output_points.float().numpy(),
                  dof_names=list(s.skeleton.dof_names), angles=A.float().numpy(), valid=valid.numpy().astype(bool),
                  confidence=np.ones((T, len(s.skeleton.output_names)), dtype=np.float32),
                  marker_names=list(s.det.marker_names), markers3d=markers3d.float().numpy(),
                  extra={"particle_spread_m": spread.numpy().astype(np.float32),
                         "markers3d_body": body.float().numpy(), "markers3d_source": source.numpy(),
                         "reinitialised": restarted.numpy().astype(bool),
                         "body_urdf": np.asarray(s.skeleton.urdf_text)})
    return MarkerTrack(poses, seconds)


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


def _lost(apf: MarkerAPF, angles: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """Which subjects' estimates ``angles (Q, D)`` have lost the body ``(Q,)``, judged on the markers that two
    views triangulate this frame (``X (Q, M, 3)``, NaN where not; at least ``LOST_MIN_MARKERS``): more than
    ``LOST_SHARE`` of them lie farther than ``LOST_M`` from the estimate's, or more than half of one limb's (at
    least ``LOST_LIMB_MARKERS``), or their median distance (the lower middle one of an even count) is over
    ``LOST_MEDIAN_M``. The particles' spread, the paper's test, barely grows when the whole cloud follows a wrong
    pose (docs/results.md, "Marker-based capture")."""
    model = apf.markers_all(angles.double()[:, None])[..., 0]  # (Q, M, 3)
    seen = torch.isfinite(X).all(-1) & apf.marker_mask[:, :X.shape[1]].to(X.device)
    dist = (model[:, :X.shape[1]].to(X) - X).norm(dim=-1)  # (Q, M), NaN where not triangulated
    far = (dist > LOST_M) & seen
    count = seen.sum(1)
    median = torch.where(seen, dist, math.nan).nanmedian(1).values
    # each limb's markers (parts 1-4; 0 the trunk): a limb stuck in another place is lost too
    part = apf.marker_part[:, :X.shape[1]].to(X.device)
    limbs = torch.arange(1, len(LIMBS) + 1, device=X.device)[:, None, None] == part  # (4, Q, M)
    limb_seen, limb_far = (limbs & seen).sum(-1), (limbs & far).sum(-1)  # (4, Q)
    limb_lost = ((limb_seen >= LOST_LIMB_MARKERS) & (limb_far > 0.5 * limb_seen)).any(0)
    return (count >= LOST_MIN_MARKERS) & ((far.sum(1) > LOST_SHARE * count) | (median > LOST_MEDIAN_M) | limb_lost)


def _restart(apf: MarkerAPF, subject: int, angles: torch.Tensor, X: torch.Tensor, first: torch.Tensor
             ) -> torch.Tensor:
    """The pose of ``subject`` whose markers best fit the triangulated ``X (M, 3)`` (padded rows NaN): inverse
    kinematics from the lost estimate and from the first frame's pose moved onto the markers at four headings, all
    at once; the least error kept."""
    m = apf.num_markers[subject]
    X = X[:m]
    seen = torch.isfinite(X).all(-1)
    centre = X[seen].mean(0)
    starts = [angles.double()]
    for k in range(4):
        a = first.double().clone()
        a[:2] = centre[:2]
        a[3] = first[3] + k * math.pi / 2
        starts.append(a)
    S = torch.stack(starts)
    fit = fit_poses_to_markers(apf.skeletons[subject], apf.marker_sets[subject], S, X[None].expand(S.shape[0], -1, -1))
    err = (apf.markers(fit, subject) - X).norm(dim=-1)[:, seen].mean(-1)
    return fit[int(err.argmin())]
