"""Frames read and observed, batch by batch, in this process or ahead of the tracker in a worker process.

Tracking a frame is many small tensor operations that one core runs about as fast as several, and the
observation (decoding, background test, occupancy) is a few large ones. On a CPU the two overlap well in two
processes: :func:`observe_batches` with ``workers=1`` reads and observes in a spawned worker (a
:class:`torch.utils.data.DataLoader` over an :class:`~torch.utils.data.IterableDataset`) while the caller
tracks the frames already observed, each process with its own share of the cores. A thread would not do:
the tracker's Python holds the GIL between its small operations (measured: no gain). The worker is spawned,
not forked: a child forked from a process whose OpenMP and OpenCV threads have run can deadlock (a forked
prototype hung in its first pooled observation). Spawning costs the worker's start, about 2-3 s (importing
torch); sources pickle without their decoders and re-open in the worker.

Thread shares (``workers=1``): the caller keeps one intra-op thread for the duration of the iteration, the
worker gets the other ``n - 1`` of the ``n`` it had (at least one), and OpenCV's and FFmpeg's own thread pools
are limited to one thread in the worker. The tracker's small operations gain nothing from more threads, and
oversubscribed cores cost more than they give: on the 2-core machine a tracker left at two threads next to a
busy process ran 3.8x slower (18.7 -> 70 ms per frame), its threads waiting for each other, and a worker given
both threads next to the tracker observed a 1.5 cm hull slower than with one. On two cores the stream pays
where observing and tracking cost about the same and the observation gains little from a second thread (the
hull: 23-26 -> 37 frames/s); the Bayesian grid at 64^3 over 8 cameras at 640x480 observes at half the speed
on one thread and runs faster in turn (``scripts/bench_track.py`` prints both).
"""

from __future__ import annotations

import logging
import os
import time
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


class _ObservedFrames(IterableDataset):
    """The frames of ``folder`` in ``[start, stop)``, observed batch by batch (picklable, for a worker)."""

    def __init__(self, folder: SequenceFolder, observer: Observer, start: int, stop: int, batch: int,
                 device: torch.device | str | None, keep_images: int, cell_m: float = 0.0,
                 threads: int | None = None) -> None:
        super().__init__()
        self.folder, self.observer, self.cell_m = folder, observer, cell_m
        self.start, self.stop, self.batch, self.device = start, stop, batch, device
        self.keep_images, self.threads = keep_images, threads

    def __iter__(self) -> Iterator[ObservedBatch | InputError]:
        if self.threads is not None:  # in a worker process: its share of the cores, and nothing more
            torch.set_num_threads(self.threads)
            import cv2

            cv2.setNumThreads(1)
            os.environ.setdefault("OPENCV_FFMPEG_CAPTURE_OPTIONS", "threads;1")  # read as each video opens
        W, H = (int(v) for v in self.observer.rig.image_size_wh[0].tolist())
        try:
            with torch.no_grad():
                for fb in self.folder.iter_batches(self.batch, self.start, self.stop, device=self.device,
                                                   size_wh=(W, H)):
                    t0 = time.perf_counter()
                    observations = self.observer(fb.images, fb.valid)
                    if self.cell_m > 0:
                        observations = [o.pooled(self.cell_m) for o in observations]
                    seconds = time.perf_counter() - t0
                    k = self.keep_images
                    images = [fb.images[i] if k and (int(t) - self.start) % k == 0 else None
                              for i, t in enumerate(fb.frame_index.tolist())]
                    yield ObservedBatch(fb.frame_index, fb.valid, observations, images, seconds)
        except InputError as exc:  # handed over as it is, not wrapped in the DataLoader's worker traceback
            if self.threads is None:
                raise
            yield exc


def observe_batches(folder: SequenceFolder, observer: Observer, start: int, stop: int, batch: int = 4,
                    device: torch.device | str | None = None, keep_images: int = 0, workers: int = 0,
                    cell_m: float = 0.0, worker_threads: int | None = None) -> Iterator[ObservedBatch]:
    """Read and observe frames ``[start, stop)`` of ``folder``, ``batch`` at a time, in order.

    Args:
        folder: the sequence. observer: the observation model at the processing size (frames are read at its
            rig's size).
        device: where frames and observations live (None: CPU).
        keep_images: also hand out the images of every ``keep_images``-th frame from ``start`` (0: none), e.g.
            the frames a logger draws on.
        workers: 0 observes in this process; 1 in a worker process running ahead of the caller (CPU only: on
            another device, or from inside a worker, this falls back to 0).
        cell_m: the observations' voxels merged per cell of this size
            (:meth:`~torchtrack.tracking.observation.VoxelObservation.pooled`; 0: as observed), where they are
            observed: the tracker's ``em_cell_m``.
        worker_threads: the worker's intra-op threads (default: one less than the caller's, at least one).

    Yields:
        :class:`ObservedBatch` es.

    Raises:
        InputError: as the reader and the observer raise it, from whichever process ran them.
    """
    if workers not in (0, 1):
        raise InputError(f"observation workers must be 0 or 1, got {workers}")
    on_cpu = torch.device(device or "cpu").type == "cpu" and next(
        (b.device.type == "cpu" for b in observer.buffers()), True)
    if workers and not on_cpu:
        log.info("observation on %s: in this process (a worker process observes on the CPU only)", device)
        workers = 0
    if workers and torch.utils.data.get_worker_info() is not None:
        workers = 0
    if not workers:
        yield from _ObservedFrames(folder, observer, start, stop, batch, device, keep_images, cell_m)
        return
    threads = torch.get_num_threads()
    frames = _ObservedFrames(folder, observer, start, stop, batch, None, keep_images, cell_m,
                             worker_threads or max(1, threads - 1))
    loader = DataLoader(frames, batch_size=None, num_workers=1, prefetch_factor=PREFETCH_BATCHES,
                        multiprocessing_context="spawn")
    torch.set_num_threads(1)
    it = iter(loader)
    try:
        for item in it:
            if isinstance(item, InputError):
                raise item
            yield item
    finally:
        del it  # stops the worker
        torch.set_num_threads(threads)
