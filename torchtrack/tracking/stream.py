"""Frames read and observed, batch by batch, in this process or ahead of the tracker in a worker process.

Tracking a frame is many small tensor operations that one core runs about as fast as several, and the observation
(decoding, background test, occupancy) is a few large ones. On a CPU the two overlap well in two processes:
:func:`observe_batches` with a worker reads and observes in a spawned :class:`ObservationWorker` while the caller
tracks the frames already observed, each process with its own share of the cores. A thread would not do: the
tracker's Python holds the GIL between its small operations (a threaded version gained nothing; docs/results.md,
"Tried and dropped"). The worker is spawned, not forked: a child forked from a process whose OpenMP and OpenCV
threads have run can deadlock. Spawning costs a few seconds (importing torch), so a run of several passes over a
sequence (background refinement, body refit) keeps one worker for all of them, and the worker keeps the frames it
decoded (:meth:`~torchtrack.io.sequence.SequenceFolder.cache_frames`, up to ``FRAME_CACHE_BYTES``): a later pass
neither starts a process nor decodes again. Sources pickle without their decoders and re-open in the worker.

Thread shares (``workers=1``): the caller keeps one intra-op thread for the duration of the iteration, the worker
gets the other ``n - 1`` of the machine's ``n`` (at least one), and OpenCV's own thread pool and FFmpeg's decoder
threads are limited to one in the worker (``OPENCV_FFMPEG_THREADS``, unless the environment sets it). The
tracker's small operations gain nothing from more threads, and oversubscribed cores cost more than they give (a
tracker's threads next to a busy process wait for each other). The stream pays where observing and tracking cost
about the same and the observation gains little from a second thread; where the observation is the larger share
and scales with threads it may not (``scripts/bench_track.py`` prints both; docs/results.md, "Speed").
"""

from __future__ import annotations

import logging
import os
import pickle
import queue
import time
import traceback
import warnings
from collections.abc import Iterator
from multiprocessing.reduction import ForkingPickler
from typing import NamedTuple

import torch

from torchtrack.checks import InputError
from torchtrack.io.sequence import SequenceFolder
from torchtrack.tracking.observation import Observer, VoxelObservation

log = logging.getLogger(__name__)

#: batches the worker may run ahead of the tracker
PREFETCH_BATCHES = 4
#: decoded frames a worker keeps for later passes over a sequence (uint8 at the processing size: the real Pose2Sim
#: demo's 100 frames of 4 cameras at a quarter of 1088 x 1920 take 157 MB); frames beyond it are decoded each pass
FRAME_CACHE_BYTES = 1 << 30
#: seconds between checks that the worker is still alive while waiting for its next batch
_POLL_S = 1.0
#: torch's intra-op threads when this module was imported (its default: the machine's cores), before a caller
#: such as :func:`~torchtrack.tracking.pipeline.track` lowered its own
MACHINE_THREADS = torch.get_num_threads()


class ObservedBatch(NamedTuple):
    """One batch of observed frames.

    Attributes:
        frame_index: (B,) int64 frame numbers. valid: (B, C) bool, the cameras whose frame was readable.
        observations: B :class:`~torchtrack.tracking.observation.VoxelObservation` s.
        images: per frame the (C, 3, H, W) RGB images where they were asked for (``keep_images``), else None.
        seconds: time the batch's observation took (reading excluded), in the process that ran it.
    """

    frame_index: torch.Tensor
    valid: torch.Tensor
    observations: list[VoxelObservation]
    images: list[torch.Tensor | None]
    seconds: float


class _Warned(NamedTuple):
    """A warning raised in the worker, to be raised again in the caller where it was raised."""

    category: type[Warning]
    message: str
    filename: str
    lineno: int

    @classmethod
    def of(cls, w: warnings.WarningMessage) -> _Warned:
        category = w.category
        try:  # a class the caller cannot import would be lost with its item
            pickle.dumps(category)
        except Exception:  # noqa: BLE001 (whatever pickling raises)
            category = UserWarning
        return cls(category, str(w.message), w.filename, w.lineno)


class _Failed(NamedTuple):
    """An exception other than ``InputError`` raised in the worker: its type and traceback, as text."""

    kind: str
    text: str


_END = "end"  # the worker's last item of a job


class _ObservedFrames:
    """Every ``step``-th frame of ``folder`` in ``[start, stop)``, observed batch by batch (picklable, for a
    worker)."""

    def __init__(self, folder: SequenceFolder, observer: Observer, start: int, stop: int, batch: int,
                 device: torch.device | str | None, keep_images: int, cell_m: float = 0.0, step: int = 1) -> None:
        self.folder, self.observer, self.cell_m = folder, observer, cell_m
        self.start, self.stop, self.batch, self.device, self.step = start, stop, batch, device, step
        self.keep_images = keep_images

    def __iter__(self) -> Iterator[ObservedBatch]:
        W, H = (int(v) for v in self.observer.rig.image_size_wh[0].tolist())
        k = self.keep_images
        for fb in self.folder.iter_batches(self.batch, self.start, self.stop, device=self.device, size_wh=(W, H),
                                           step=self.step):
            t0 = time.perf_counter()
            with torch.no_grad():
                observations = self.observer(fb.images, fb.valid)
                if self.cell_m > 0:
                    observations = [o.pooled(self.cell_m) for o in observations]
            seconds = time.perf_counter() - t0
            images = [fb.images[i].clone() if k and (int(t) - self.start) // self.step % k == 0 else None
                      for i, t in enumerate(fb.frame_index.tolist())]  # a copy: not the whole batch kept alive
            yield ObservedBatch(fb.frame_index, fb.valid, observations, images, seconds)


def _serve(jobs, results, current, threads: int, cache_bytes: int, debug: bool) -> None:
    """The worker process: observe each job's frames into ``results`` until a None job; stop a job early when
    ``current`` no longer names it (the caller left it). Its sequences are kept, with their decoded frames."""
    # its share of the cores and nothing more (OpenCV's pool, FFmpeg's decoder threads, read as each video
    # opens), its warnings handed to the caller; with the caller's -v its debug lines (each undecodable frame,
    # FFmpeg's messages) go to stderr as the caller's do
    if debug:
        logging.basicConfig(level=logging.DEBUG, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(threads)
    import cv2

    cv2.setNumThreads(1)
    os.environ.setdefault("OPENCV_FFMPEG_THREADS", "1")
    kept: tuple[tuple, SequenceFolder] | None = None  # the last sequence, with its decoded frames
    while (job := jobs.get()) is not None:
        number, payload = job
        try:
            frames = ForkingPickler.loads(payload)
        except Exception as exc:  # noqa: BLE001 (e.g. a class this process cannot import)
            results.put((number, _Failed(type(exc).__name__, traceback.format_exc())))
            results.put((number, _END))
            continue
        key = (str(frames.folder.root), tuple(map(str, frames.folder.camera_names)), frames.folder.num_frames)
        if kept is None or kept[0] != key:  # one sequence's frames at a time
            frames.folder.cache_frames(cache_bytes)
            kept = (key, frames.folder)
        frames.folder = kept[1]
        with warnings.catch_warnings(record=True) as caught:  # under the process's default filters
            try:
                for item in frames:
                    for w in caught:
                        results.put((number, _Warned.of(w)))
                    caught.clear()
                    if current.value != number:
                        break
                    results.put((number, item))
            except InputError as exc:  # handed over as it is
                results.put((number, exc))
            except Exception as exc:  # noqa: BLE001 (any failure reaches the caller, the worker goes on)
                results.put((number, _Failed(type(exc).__name__, traceback.format_exc())))
            for w in caught:
                results.put((number, _Warned.of(w)))
        results.put((number, _END))


class ObservationWorker:
    """A spawned process that reads and observes frames ahead of the tracker, job after job
    (:func:`observe_batches` with ``workers=`` this worker): started once for several passes over a sequence, it
    keeps the sequence's decoded frames for the passes after the first (up to ``cache_bytes``).

    Use it as a context manager (or call :meth:`close`). A script that starts one must guard its entry point with
    ``if __name__ == "__main__":``, as for any spawned process. Warnings the worker raises (e.g. an undecodable
    frame) are raised again in the caller; its log records go to its own stderr.

    Args:
        threads: the worker's intra-op threads (default: one less than the machine's, at least one: the caller
            keeps one while it iterates).
        cache_bytes: decoded frames kept per sequence (0: none).
    """

    def __init__(self, threads: int | None = None, cache_bytes: int = FRAME_CACHE_BYTES) -> None:
        if not ((threads is None or threads >= 1) and cache_bytes >= 0):
            raise InputError(f"ObservationWorker: threads must be >= 1 and cache_bytes >= 0, got {threads}, "
                             f"{cache_bytes}")
        ctx = torch.multiprocessing.get_context("spawn")
        self._jobs, self._results = ctx.Queue(), ctx.Queue(maxsize=PREFETCH_BATCHES)
        self._current = ctx.Value("q", 0, lock=False)
        self._number = 0
        debug = logging.getLogger().getEffectiveLevel() <= logging.DEBUG  # the caller's -v
        self._process = ctx.Process(target=_serve, daemon=True, name="torchtrack-observe",
                                    args=(self._jobs, self._results, self._current,
                                          threads or max(1, MACHINE_THREADS - 1), cache_bytes, debug))
        self._process.start()

    def __enter__(self) -> ObservationWorker:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def alive(self) -> bool:
        return self._process.is_alive()

    def close(self) -> None:
        """Stop the worker (what it was doing is dropped)."""
        if self._process.is_alive():
            self._current.value = -1
            self._jobs.put(None)
            self._drain()
            self._process.join(timeout=10)
            if self._process.is_alive():
                self._process.kill()
        self._process.join()
        for q in (self._jobs, self._results):
            q.close()
            q.join_thread()

    def _drain(self) -> None:
        """Take what is queued, so that a worker blocked on a full queue moves on. An item whose tensors a stopping
        worker no longer shares fails to unpickle once taken: it is dropped all the same."""
        for _ in range(4 * PREFETCH_BATCHES + 16):  # bounded: a closed queue raises the same way every time
            try:
                self._results.get_nowait()
            except queue.Empty:
                return
            except Exception:  # noqa: BLE001 (EOFError, ConnectionError, ...: the item is gone either way)
                continue

    def observe(self, frames: _ObservedFrames) -> Iterator[ObservedBatch]:
        """The observed batches of ``frames``, in order."""
        if not self._process.is_alive():
            raise InputError(f"the observation worker has stopped (exit code {self._process.exitcode})")
        self._number += 1
        number = self._current.value = self._number  # the worker stops any earlier job at its next batch
        try:  # pickled here: the queue's own pickling, in its feeder thread, would fail silently
            self._jobs.put((number, bytes(ForkingPickler.dumps(frames))))
        except (pickle.PicklingError, AttributeError, TypeError) as exc:
            raise InputError(f"{frames.folder.root}: the observation worker cannot take the sequence, its folder and "
                             f"observer do not pickle ({exc}); observe in this process (workers=0)") from exc
        try:
            while True:
                try:
                    got, item = self._results.get(timeout=_POLL_S)
                except queue.Empty:
                    if not self._process.is_alive():
                        raise InputError(f"{frames.folder.root}: the observation worker died (exit code "
                                         f"{self._process.exitcode})") from None
                    continue
                if got != number:
                    continue  # what an earlier, abandoned job still had queued
                if isinstance(item, str) and item == _END:
                    return
                if isinstance(item, _Warned):
                    warnings.warn_explicit(item.message, item.category, item.filename, item.lineno)
                elif isinstance(item, InputError):
                    raise item
                elif isinstance(item, _Failed):
                    raise RuntimeError(f"{frames.folder.root}: the observation worker failed with {item.kind}:\n"
                                       f"{item.text}")
                else:
                    yield item
        finally:
            if self._current.value == number:
                self._current.value = 0  # left early or done: the worker drops the rest


def observe_batches(folder: SequenceFolder, observer: Observer, start: int, stop: int, batch: int = 4,
                    device: torch.device | str | None = None, keep_images: int = 0,
                    workers: int | ObservationWorker = 0, cell_m: float = 0.0,
                    worker_threads: int | None = None, step: int = 1) -> Iterator[ObservedBatch]:
    """Read and observe every ``step``-th frame of ``folder`` in ``[start, stop)``, ``batch`` at a time, in order.

    Args:
        folder: the sequence. observer: the observation model at the processing size (frames are read at its
            rig's size).
        device: where frames and observations live (None: CPU).
        keep_images: also hand out the images of every ``keep_images``-th frame observed (0: none), e.g.
            the frames a logger draws on.
        workers: 0 observes in this process; an :class:`ObservationWorker` in that worker, running ahead of the
            caller; 1 in a worker started for this call (2-3 s) and stopped at its end. CPU only: for an observer
            or device elsewhere this falls back to 0.
        cell_m: the observations' voxels merged per cell of this size
            (:meth:`~torchtrack.tracking.observation.VoxelObservation.pooled`; 0: as observed), where they are
            observed: the tracker's ``em_cell_m``.
        worker_threads: with ``workers=1``, the worker's intra-op threads (see :class:`ObservationWorker`).

    Yields:
        :class:`ObservedBatch` es.

    Raises:
        InputError: bad arguments; as the reader and the observer raise it, from whichever process ran them.
    """
    if not isinstance(workers, ObservationWorker) and workers not in (0, 1):
        raise InputError(f"observation workers must be 0 or 1, got {workers}")
    if not (keep_images >= 0 and cell_m >= 0 and (worker_threads is None or worker_threads >= 1) and step >= 1):
        raise InputError(f"observe_batches: keep_images and cell_m must be >= 0, worker_threads and step >= 1, got "
                         f"{keep_images}, {cell_m}, {worker_threads}, {step}")
    where = {b.device for b in observer.buffers()} | {torch.device(device or "cpu")}
    if workers and any(d.type != "cpu" for d in where):
        log.info("observation on %s: in this process (a worker process observes on the CPU only)",
                 ", ".join(sorted(map(str, where))))
        workers = 0
    if not workers:
        yield from _ObservedFrames(folder, observer, start, stop, batch, device, keep_images, cell_m, step)
        return
    frames = _ObservedFrames(folder, observer, start, stop, batch, None, keep_images, cell_m, step)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        if isinstance(workers, ObservationWorker):
            yield from workers.observe(frames)
        else:
            with ObservationWorker(worker_threads) as worker:
                yield from worker.observe(frames)
    finally:
        torch.set_num_threads(threads)
