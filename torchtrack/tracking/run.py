"""Tracking a whole sequence folder: read, observe, track, log; the loop behind `torchtrack track`."""

from __future__ import annotations

import contextvars
import logging
import threading
import time
from collections.abc import Iterator
from contextlib import closing
from typing import NamedTuple

import numpy as np
import torch

from torchtrack.checks import InputError
from torchtrack.io.poses import Poses
from torchtrack.io.sequence import SequenceFolder, min_readable_cameras
from torchtrack.tracking.markerless import MarkerlessTracker
from torchtrack.tracking.observation import Observer, VoxelObservation
from torchtrack.tracking.stream import ObservationWorker, observe_batches

log = logging.getLogger(__name__)


def track_sequence(folder: SequenceFolder, observer: Observer, tracker: MarkerlessTracker, start: int = 0,
                   stop: int | None = None, batch: int = 4, device: torch.device | str | None = None,
                   logger=None, log_every: int = 10, progress: bool = True, desc: str = "track",
                   workers: int | ObservationWorker = 0, step: int = 1) -> tuple[Poses, float]:
    """Track frames ``[start, stop)`` of ``folder`` (every ``step``-th: ``start, start + step, ..``).

    A frame is tracked from the cameras whose frame is readable (a camera that ends early or stops decoding is
    left out of the frames it lacks: the occupancy takes no evidence from it), when at least
    :func:`~torchtrack.io.sequence.min_readable_cameras` are; with fewer it is not tracked and comes out
    ``valid = False``, as does a frame with nobody in the volume. Cameras left out are named in one warning per
    camera and in ``extra['cameras_valid']``. Errors of the tracker name the frame.

    Inside :func:`lockstep_passes` (several sequences' pipelines, each in a thread of its own), the pass is not run
    here but handed to the lockstep driver, which tracks it together with the other sequences' passes.

    Args:
        folder: the sequence. observer: the observation model at the processing size (its rig's size is the
            size frames are read at). tracker: a fresh or initialised :class:`MarkerlessTracker`.
        logger: a :class:`~torchtrack.logging.RunLogger` or None; it gets per-frame scalars and, every
            ``log_every`` frames, every camera's image with the pose drawn and the voxels with the skeleton (the
            voxels EM fitted: merged per cell with the tracker's ``em_cell_m``).
        desc: the progress bar's label.
        workers: an :class:`~torchtrack.tracking.stream.ObservationWorker` reads and observes the frames ahead of
            the tracker (CPU); 1 in a worker started for this track (2-3 s; a calling script needs an ``if __name__
            == "__main__":`` guard; see :func:`~torchtrack.tracking.stream.observe_batches`); 0 in this process.
        step: track every ``step``-th frame, as a sequence of ``fps / step`` frames a second (the tracker's
            prediction and its races in seconds follow); the poses hold those frames (``frame_index``).

    Returns:
        the poses (docs/formats.md; ``extra`` holds ``subject_height_m``, ``observation_model``,
        ``ik_residual_m``, ``explained``, ``reinitialised``, ``camera_names`` and ``cameras_valid`` (T, C), and
        ``body_urdf``, the subject's fitted body as URDF text, once initialised) and the seconds taken.
    """
    from tqdm import tqdm

    scheduler = _SCHEDULER.get()
    if scheduler is not None:
        return scheduler.run(_Pass(folder, observer, tracker, start, stop, batch, device, logger, log_every, 0, step))
    one = _Pass(folder, observer, tracker, start, stop, batch, device, logger, log_every, workers, step)
    # closing: a tracking error (its traceback holds this frame) must not keep the worker and thread share
    with tqdm(total=one.num_frames, unit="frame", desc=desc, disable=not progress) as bar, closing(one):
        for frame in one.frames():
            t1 = time.perf_counter()
            res = one.guard(frame, lambda: tracker.skip() if frame.obs is None else tracker.step(frame.obs))
            one.record(frame, res, time.perf_counter() - t1)
            bar.update(1)
            bar.set_postfix(valid=f"{one.valid[:frame.k + 1].mean():.0%}", res_mm=f"{1e3 * res.residual_m:.0f}")
    return one.finish()


class _Frame(NamedTuple):
    """One frame of a pass: its index in the pass and in the sequence, its observation (None: too few readable
    cameras, not tracked), its images where kept, and its share of the time its batch took to come."""

    k: int
    t: int
    obs: VoxelObservation | None
    observed: VoxelObservation
    images: torch.Tensor | None
    wait_s: float
    observe_s: float


class _Pass:
    """One track of every ``step``-th frame of ``[start, stop)`` of a sequence: its frames as they are read and
    observed, the results recorded, and the poses at the end (:func:`track_sequence`'s work, driven alone or in
    lockstep)."""

    def __init__(self, folder: SequenceFolder, observer: Observer, tracker: MarkerlessTracker, start: int,
                 stop: int | None, batch: int, device, logger, log_every: int,
                 workers: int | ObservationWorker, step: int = 1) -> None:
        self.folder, self.observer, self.tracker, self.logger = folder, observer, tracker, logger
        self.start, self.step = start, step
        self.stop = folder.num_frames if stop is None else min(stop, folder.num_frames)
        if self.stop <= start:
            raise InputError(f"{folder.root}: no frames in [{start}, {self.stop}) ({folder.num_frames} frames)")
        if not (isinstance(step, int) and step >= 1):
            raise InputError(f"track_sequence: step must be a whole number >= 1, got {step!r}")
        tracker.set_frame_rate(folder.fps / step)
        self.frame_index = np.arange(start, self.stop, step, dtype=np.int64)
        self.names = tracker.generic.output_names
        T, D, C = len(self.frame_index), tracker.generic.num_dofs, len(observer.rig.names)
        self.joints3d = np.full((T, len(self.names), 3), np.nan, np.float32)
        self.angles = np.full((T, D), np.nan, np.float32)
        self.valid = np.zeros(T, bool)
        self.confidence = np.zeros((T, len(self.names)), np.float32)
        self.residual = np.full(T, np.nan, np.float32)
        self.explained = np.zeros(T, np.float32)
        self.reinit = np.zeros(T, bool)
        self.version = np.zeros(T, np.int64)  # the tracker's body_version each frame was tracked in
        self.cameras_valid = np.zeros((T, C), bool)
        self.need = min_readable_cameras(C)
        self.t_start = time.perf_counter()
        self.last: int | None = None  # the last frame recorded
        keep = log_every if logger is not None else 0
        self.stream = observe_batches(folder, observer, start, self.stop, batch, device, keep, workers,
                                      cell_m=tracker.config.em_cell_m, step=step)

    @property
    def num_frames(self) -> int:
        return len(self.frame_index)

    def close(self) -> None:
        self.stream.close()

    def frames(self) -> Iterator[_Frame]:
        """The pass's frames in order, read and observed a batch at a time."""
        while True:
            t0 = time.perf_counter()
            fb = next(self.stream, None)
            if fb is None:
                return
            n = len(fb.observations)
            # per frame, its share of the time the batch took to come (reading and observing it, or waiting for
            # the worker that did): with its own tracking, the wall-clock rate
            wait = (time.perf_counter() - t0) / n
            for i, obs in enumerate(fb.observations):
                t = int(fb.frame_index[i])
                k = (t - self.start) // self.step
                self.cameras_valid[k] = fb.valid[i].cpu().numpy()
                self.version[k] = self.tracker.body_version
                enough = self.cameras_valid[k].sum() >= self.need  # too few readable cameras to carve the body
                yield _Frame(k, t, obs if enough else None, obs, fb.images[i], wait, fb.seconds / n)

    def guard(self, frame: _Frame, step):  # noqa: ANN001, ANN201
        """``step()``'s result, its errors naming the sequence and the frame (:meth:`named`)."""
        try:
            return step()
        except Exception as exc:
            raise self.named(frame, exc) from None

    def named(self, frame: _Frame | str, exc: Exception) -> Exception:
        """``exc`` raised while tracking ``frame`` (or at the place a string says), saying where: an input error's
        message names the sequence and the frame; other (numerical, device) errors get a note."""
        where = frame if isinstance(frame, str) else f"frame {frame.t}"
        if isinstance(exc, InputError):
            return InputError(f"{self.folder.root}, {where}: {exc}")
        exc.add_note(f"while tracking {self.folder.root}, {where}")
        return exc

    def _put(self, k: int, res) -> None:  # noqa: ANN001
        self.joints3d[k] = res.output_points.cpu().numpy()
        self.angles[k] = res.angles.cpu().numpy()
        self.valid[k] = res.valid
        self.confidence[k] = res.confidence.cpu().numpy() if res.valid else 0.0
        self.residual[k] = res.residual_m
        self.explained[k] = res.explained
        self.reinit[k] = res.reinitialised

    def record(self, frame: _Frame, res, seconds: float) -> None:  # noqa: ANN001
        """Store ``frame``'s result (and the frames a start race revised); log it."""
        k = self.last = frame.k
        self._put(k, res)
        self._revise(k)
        if self.logger is not None:
            _log_frame(self.logger, frame.t, frame.observed, res, frame.images, self.observer.rig,
                       frame.wait_s + seconds, frame.observe_s)

    def _revise(self, k: int) -> None:
        """The frames up to ``k`` that the tracker revised: a won start race's, or the frames tracked back."""
        revised = self.tracker.take_revised()
        for j, (r, v) in enumerate(revised):
            self._put(k - len(revised) + 1 + j, r)
            self.version[k - len(revised) + 1 + j] = v

    def finish(self) -> tuple[Poses, float]:
        """The pass's poses (re-stated in the final body) and its seconds; the reports on cameras and start."""
        tracker, rig = self.tracker, self.observer.rig
        if self.last is not None:  # a start in the last second: its race and track back at the end
            try:
                tracker.finish()
            except Exception as exc:
                raise self.named("the end of the sequence", exc) from None
            self._revise(self.last)
        restate(tracker, self.angles, self.joints3d, self.version)
        if self.step == 1:  # once per folder: from a track of every frame (after passes with a step, one follows)
            _report_cameras(self.folder, list(rig.names), self.cameras_valid, self.frame_index, self.need)
            _report_start(self.folder, tracker, self.reinit, self.frame_index)
        elapsed = time.perf_counter() - self.t_start
        extra = {"subject_height_m": np.float64(tracker.height_m or np.nan),
                 "observation_model": np.asarray(self.observer.model), "ik_residual_m": self.residual,
                 "explained": self.explained, "reinitialised": self.reinit,
                 "camera_names": np.asarray(list(rig.names)), "cameras_valid": self.cameras_valid}
        if tracker.subject is not None:  # the subject's body, for a later --init-pose (de Bem's reusable start)
            extra["body_urdf"] = np.asarray(tracker.subject.skeleton.urdf_text)
        poses = Poses(fps=self.folder.fps, frame_index=self.frame_index.copy(),
                      joint_names=list(self.names), joints3d=self.joints3d, dof_names=list(tracker.generic.dof_names),
                      angles=self.angles, valid=self.valid, confidence=self.confidence, extra=extra)
        return poses, elapsed


def track_lockstep(passes: list[_Pass], progress: bool = True) -> list[tuple[Poses, float] | BaseException]:
    """Run several sequences' passes frame by frame in lockstep (:class:`~torchtrack.tracking.lockstep.Lockstep`:
    one batched step for all that track as usual); a pass whose sequence fails (its reading, its observation, its
    tracker's own step) ends with its error while the others go on. Each pass's poses and seconds, or its error."""
    from tqdm import tqdm

    from torchtrack.tracking.lockstep import Lockstep

    out: list[tuple[Poses, float] | BaseException | None] = [None] * len(passes)
    lockstep = Lockstep([p.tracker for p in passes])
    streams = {i: p.frames() for i, p in enumerate(passes)}
    total = sum(p.num_frames for p in passes)
    with tqdm(total=total, unit="frame", desc=f"track {len(passes)} in lockstep", disable=not progress) as bar:
        while streams:
            frames: dict[int, _Frame] = {}
            for i in list(streams):
                try:
                    frame = next(streams[i], None)
                except Exception as exc:  # noqa: BLE001 - a sequence that cannot be read fails alone
                    frame, out[i] = None, exc
                if frame is None:
                    del streams[i]
                    passes[i].close()
                    if out[i] is None:
                        try:
                            out[i] = passes[i].finish()
                        except Exception as exc:  # noqa: BLE001 - its end (the track back) fails alone too
                            out[i] = exc
                    continue
                frames[i] = frame
            if not frames:
                break
            t1 = time.perf_counter()
            results, errors = lockstep.step({i: f.obs for i, f in frames.items()})
            dt = (time.perf_counter() - t1) / len(frames)
            for i, frame in frames.items():
                if i in errors:  # this sequence fails alone, naming the frame
                    out[i] = passes[i].named(frame, errors[i])
                    del streams[i]
                    passes[i].close()
                    continue
                passes[i].record(frame, results[i], dt)
            bar.update(len(frames))
    return out


class _Scheduler:
    """Collects the track passes of several sequences' pipelines, each running in a thread of its own, and runs
    them in lockstep once every pipeline still going waits for one (:func:`lockstep_passes`)."""

    def __init__(self, pipelines: int, progress: bool) -> None:
        self.active, self.progress = pipelines, progress
        self.pending: list[tuple[_Pass, list]] = []
        self.cond = threading.Condition()

    def run(self, one: _Pass) -> tuple[Poses, float]:
        """Called from a pipeline's thread: hand the pass over and wait for its result."""
        slot: list = []
        with self.cond:
            self.pending.append((one, slot))
            self.cond.notify_all()
            self.cond.wait_for(lambda: bool(slot))
        result = slot[0]
        if isinstance(result, BaseException):
            raise result
        return result

    def done(self) -> None:
        """Called from a pipeline's thread as it ends (finished or failed)."""
        with self.cond:
            self.active -= 1
            self.cond.notify_all()

    def serve(self) -> None:
        """In the calling thread: run the passes in lockstep, round after round, until every pipeline ended."""
        while True:
            with self.cond:
                self.cond.wait_for(lambda: self.active == 0 or len(self.pending) >= self.active)
                if self.active == 0 and not self.pending:
                    return
                batch, self.pending = self.pending, []
            try:
                results = track_lockstep([p for p, _ in batch], self.progress)
            except BaseException as exc:  # noqa: BLE001 - every pass of the round fails with it
                results = [exc] * len(batch)
            with self.cond:
                for (_, slot), res in zip(batch, results):
                    slot.append(res)
                self.cond.notify_all()


_SCHEDULER: contextvars.ContextVar[_Scheduler | None] = contextvars.ContextVar("torchtrack_lockstep", default=None)


def lockstep_passes(jobs: list, progress: bool = True) -> list:
    """Run ``jobs`` (callables, e.g. each sequence's whole pipeline), each in a thread of its own, with their
    :func:`track_sequence` passes tracked together in lockstep: whenever every job still running waits for a pass,
    those passes run as one (:func:`track_lockstep`). Each job's return value, or the exception it raised."""
    scheduler = _Scheduler(len(jobs), progress)
    out: list = [None] * len(jobs)

    def work(i: int, job) -> None:  # noqa: ANN001
        _SCHEDULER.set(scheduler)
        try:
            out[i] = job()
        except BaseException as exc:  # noqa: BLE001 - kept as this job's outcome
            out[i] = exc
        finally:
            scheduler.done()

    threads = [threading.Thread(target=work, args=(i, job), daemon=True, name=f"torchtrack-seq-{i}")
               for i, job in enumerate(jobs)]
    for t in threads:
        t.start()
    scheduler.serve()
    for t in threads:
        t.join()
    return out


def _report_start(folder: SequenceFolder, tracker: MarkerlessTracker, reinit: np.ndarray,
                  frame_index: np.ndarray) -> None:
    """Warn once per folder when the start was refused on frames (they are invalid), saying why (``frame_index``:
    the frames of ``reinit``)."""
    refused = tracker.start_refusals
    if not refused or "start" in folder.reported:
        return
    folder.reported.add("start")
    started = np.flatnonzero(reinit)
    where = f"started at frame {int(frame_index[started[0]])}" if started.size else "never started"
    log.warning("%s: %s; %d earlier frame(s) with voxels were not started from (invalid), the first because: %s",
                folder.root, where, len(refused), refused[0])


def _report_cameras(folder: SequenceFolder, names: list[str], cameras_valid: np.ndarray, frame_index: np.ndarray,
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
                        frame_ranges(frame_index[missing].tolist()), need)
    few = np.flatnonzero(cameras_valid.sum(1) < need)
    if few.size and "few cameras" not in reported:
        reported.add("few cameras")
        log.warning("%s: %d frame(s) (%s) have fewer than %d readable cameras and were not tracked", folder.root,
                    few.size, frame_ranges(frame_index[few].tolist()), need)


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
