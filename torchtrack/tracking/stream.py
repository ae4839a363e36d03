"""Frames read and observed, batch by batch, in this process or ahead of the tracker in a worker process.

Tracking a frame is many small tensor operations that one core runs about as fast as several, and the observation
(decoding, background test, occupancy) is a few large ones. On a CPU the two overlap well in two processes:
:func:`observe_batches` with ``workers=1`` reads and observes in a spawned worker (a
:class:`torch.utils.data.DataLoader` over an :class:`~torch.utils.data.IterableDataset`) while the caller tracks
the frames already observed, each process with its own share of the cores. A thread would not do: the tracker's
Python holds the GIL between its small operations (a threaded version gained nothing; docs/results.md, "Tried and
dropped"). The worker is spawned, not forked: a child forked from a process whose OpenMP and OpenCV threads have
run can deadlock. Spawning costs the worker's start, a few seconds (importing torch); sources pickle without
their decoders and re-open in the worker.

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
import time
import warnings
from collections.abc import Iterator
from typing import NamedTuple

import torch
from torch.utils.data import DataLoader, IterableDataset

from torchtrack.checks import InputError
from torchtrack.io.sequence import SequenceFolder
from torchtrack.tracking.observation import Observer, VoxelObservation

log = logging.getLogger(__name__)

#: batches the worker may run ahead of the tracker
PREFETCH_BATCHES = 4
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


class _ObservedFrames(IterableDataset):
    """The frames of ``folder`` in ``[start, stop)``, observed batch by batch (picklable, for a worker)."""

    def __init__(self, folder: SequenceFolder, observer: Observer, start: int, stop: int, batch: int,
                 device: torch.device | str | None, keep_images: int, cell_m: float = 0.0,
                 threads: int | None = None) -> None:
        super().__init__()
        self.folder, self.observer, self.cell_m = folder, observer, cell_m
        self.start, self.stop, self.batch, self.device = start, stop, batch, device
        self.keep_images, self.threads = keep_images, threads
        self.debug = logging.getLogger().getEffectiveLevel() <= logging.DEBUG  # the caller's -v

    def __iter__(self) -> Iterator[ObservedBatch | _Warned | InputError]:
        if self.threads is None:
            yield from self._batches()
            return
        # in a worker process: its share of the cores and nothing more (OpenCV's pool, FFmpeg's decoder
        # threads, read as each video opens), its warnings handed to the caller; with the caller's -v its debug
        # lines (each undecodable frame, FFmpeg's messages) go to stderr as the caller's do
        if self.debug:
            logging.basicConfig(level=logging.DEBUG, format="%(levelname)s %(name)s: %(message)s")
        torch.set_num_threads(self.threads)
        import cv2

        cv2.setNumThreads(1)
        os.environ.setdefault("OPENCV_FFMPEG_THREADS", "1")
        with warnings.catch_warnings(record=True) as caught:  # under the process's default filters
            try:
                for item in self._batches():
                    yield from map(_Warned.of, caught)
                    caught.clear()
                    yield item
            except InputError as exc:  # handed over as it is, not wrapped in the DataLoader's worker traceback
                yield from map(_Warned.of, caught)
                caught.clear()
                yield exc
            yield from map(_Warned.of, caught)

    def _batches(self) -> Iterator[ObservedBatch]:
        W, H = (int(v) for v in self.observer.rig.image_size_wh[0].tolist())
        k = self.keep_images
        for fb in self.folder.iter_batches(self.batch, self.start, self.stop, device=self.device, size_wh=(W, H)):
            t0 = time.perf_counter()
            with torch.no_grad():
                observations = self.observer(fb.images, fb.valid)
                if self.cell_m > 0:
                    observations = [o.pooled(self.cell_m) for o in observations]
            seconds = time.perf_counter() - t0
            images = [fb.images[i].clone() if k and (int(t) - self.start) % k == 0 else None
                      for i, t in enumerate(fb.frame_index.tolist())]  # a copy: not the whole batch kept alive
            yield ObservedBatch(fb.frame_index, fb.valid, observations, images, seconds)


def observe_batches(folder: SequenceFolder, observer: Observer, start: int, stop: int, batch: int = 4,
                    device: torch.device | str | None = None, keep_images: int = 0, workers: int = 0,
                    cell_m: float = 0.0, worker_threads: int | None = None) -> Iterator[ObservedBatch]:
    """Read and observe frames ``[start, stop)`` of ``folder``, ``batch`` at a time, in order.

    With ``workers=1`` every call starts a worker process (2-3 s) and stops it at the end, and a script that
    calls this (or :func:`~torchtrack.tracking.run.track_sequence` with workers) must guard its entry point
    with ``if __name__ == "__main__":``, as for any spawned process. Warnings the worker raises (e.g. an
    undecodable frame) are raised again here; its log records go to its own stderr.

    Args:
        folder: the sequence. observer: the observation model at the processing size (frames are read at its
            rig's size).
        device: where frames and observations live (None: CPU).
        keep_images: also hand out the images of every ``keep_images``-th frame from ``start`` (0: none), e.g.
            the frames a logger draws on.
        workers: 0 observes in this process; 1 in a worker process running ahead of the caller (CPU only: for
            an observer or device elsewhere, or from inside a worker, this falls back to 0).
        cell_m: the observations' voxels merged per cell of this size
            (:meth:`~torchtrack.tracking.observation.VoxelObservation.pooled`; 0: as observed), where they are
            observed: the tracker's ``em_cell_m``.
        worker_threads: the worker's intra-op threads (default: one less than the machine's, at least one: the
            caller keeps one while it iterates).

    Yields:
        :class:`ObservedBatch` es.

    Raises:
        InputError: bad arguments; as the reader and the observer raise it, from whichever process ran them.
    """
    if workers not in (0, 1):
        raise InputError(f"observation workers must be 0 or 1, got {workers}")
    if not (keep_images >= 0 and cell_m >= 0 and (worker_threads is None or worker_threads >= 1)):
        raise InputError(f"observe_batches: keep_images and cell_m must be >= 0 and worker_threads >= 1, got "
                         f"{keep_images}, {cell_m}, {worker_threads}")
    where = {b.device for b in observer.buffers()} | {torch.device(device or "cpu")}
    if workers and any(d.type != "cpu" for d in where):
        log.info("observation on %s: in this process (a worker process observes on the CPU only)",
                 ", ".join(sorted(map(str, where))))
        workers = 0
    if workers and torch.utils.data.get_worker_info() is not None:
        workers = 0
    if not workers:
        yield from _ObservedFrames(folder, observer, start, stop, batch, device, keep_images, cell_m)
        return
    threads = torch.get_num_threads()
    frames = _ObservedFrames(folder, observer, start, stop, batch, None, keep_images, cell_m,
                             worker_threads or max(1, MACHINE_THREADS - 1))
    loader = DataLoader(frames, batch_size=None, num_workers=1, prefetch_factor=PREFETCH_BATCHES,
                        multiprocessing_context="spawn")
    it = None
    try:
        torch.set_num_threads(1)
        try:
            it = iter(loader)
        except (pickle.PicklingError, AttributeError, TypeError) as exc:
            raise InputError(f"{folder.root}: the observation worker cannot be started, its folder and observer do "
                             f"not pickle ({exc}); observe in this process (workers=0)") from exc
        for item in it:
            if isinstance(item, _Warned):
                warnings.warn_explicit(item.message, item.category, item.filename, item.lineno)
            elif isinstance(item, InputError):
                raise item
            else:
                yield item
    finally:
        if it is not None and hasattr(it, "_shutdown_workers"):
            it._shutdown_workers()  # also when an exception that holds the iterator is kept by the caller
        del it
        torch.set_num_threads(threads)
