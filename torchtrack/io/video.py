"""Frame sources and writers: video files and image folders, RGB ``uint8`` at this edge.

OpenCV (with the FFmpeg it bundles) does all decoding and encoding; it is imported inside the functions, never
at package import time. Everything here speaks **RGB** ``(H, W, 3) uint8`` numpy arrays: BGR exists only on the
line that calls OpenCV.

Frame access is **sequential**: a :class:`VideoFileSource` never seeks with ``CAP_PROP_POS_FRAMES`` (FFmpeg
seeks to key frames and, on damaged streams, fails where sequential decoding still works); it decodes forward
and re-opens the file to go back. Readers are meant to move forward in batches.

Frame counts of video files: the container's ``CAP_PROP_FRAME_COUNT`` is an estimate for some files. By default
it is trusted (opening stays fast for long videos) and frames that then fail to decode are reported as invalid;
``verify_frame_count=True`` decodes the whole file once at open time and uses the count of decodable frames.

Damaged frames: ``read(..., strict=True)`` raises :class:`~torchtrack.checks.InputError` naming the file and the
frame index; ``strict=False`` returns a validity mask instead (invalid frames are zero-filled) so a tracker can
skip them. A file that cannot be opened, or whose first frame does not decode, is an ``InputError`` at open time.
"""

from __future__ import annotations

import abc
import contextlib
import logging
import os
import re
import sys
import tempfile
import warnings
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from torchtrack.checks import InputError, ShapeError
from torchtrack.io.atomic import atomic_dir, atomic_path

logger = logging.getLogger(__name__)

#: File suffixes read as video files (lower case).
VIDEO_SUFFIXES: tuple[str, ...] = (".mp4", ".avi", ".mov", ".mkv", ".m4v")
#: File suffixes read as frames of an image folder (lower case).
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg")
#: Codecs tried by :func:`write_video`, in order. The opencv-python wheels' FFmpeg has no H.264 encoder
#: (``avc1`` fails to open here), so MPEG-4 Part 2 (``mp4v``) is the portable choice.
DEFAULT_FOURCCS: tuple[str, ...] = ("mp4v",)


class DataWarning(UserWarning):
    """Input data that can be used but differs from what was expected (sizes, counts, names)."""


# ----------------------------------------------------------------------------------------------- writers


def _check_rgb_frame(frame: np.ndarray, index: int, size_hw: tuple[int, int] | None) -> np.ndarray:
    frame = np.asarray(frame)
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise ShapeError(f"frame {index}: expected an (H, W, 3) uint8 RGB array, got {frame.dtype} "
                         f"{tuple(frame.shape)}")
    if size_hw is not None and frame.shape[:2] != size_hw:
        raise ShapeError(f"frame {index}: expected shape {size_hw + (3,)} like frame 0, got {tuple(frame.shape)}")
    return frame


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float,
                fourccs: Sequence[str] = DEFAULT_FOURCCS) -> int:
    """Write RGB frames to a video file atomically (a temporary file beside ``path``, renamed at the end).

    Args:
        path: target file; its suffix picks the container (``.mp4`` for the sequence format).
        frames: iterable of ``(H, W, 3)`` uint8 RGB arrays, all of one size; H and W must be even (MPEG-4 with
            4:2:0 chroma would silently crop an odd size).
        fps: frame rate written into the container.
        fourccs: codecs to try in order; the first one OpenCV's FFmpeg can open is used, and falling back to a
            later one is logged as a warning.

    Returns:
        The number of frames written.

    Raises:
        ShapeError: a frame of the wrong dtype or shape.
        InputError: no frames, an odd size, a non-positive fps.
        RuntimeError: none of ``fourccs`` can be opened for writing (names them). ``path`` is then untouched.
    """
    import cv2

    path = Path(path)
    if not fps > 0:
        raise InputError(f"write_video {path}: fps must be positive, got {fps}")
    it = iter(frames)
    try:
        first = _check_rgb_frame(next(it), 0, None)
    except StopIteration:
        raise InputError(f"write_video {path}: no frames to write") from None
    h, w = first.shape[:2]
    if h % 2 or w % 2:
        raise InputError(f"write_video {path}: width and height must be even for 4:2:0 video, got W={w}, H={h}")
    count = 0
    with atomic_path(path) as tmp:  # the temporary name keeps the suffix: FFmpeg picks the container from it
        writer = None
        for i, code in enumerate(fourccs):
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*code), float(fps), (w, h))
            if writer.isOpened():
                if i > 0:
                    logger.warning("write_video %s: codec %r not available, fell back to %r", path, fourccs[0], code)
                break
            writer.release()
            writer = None
        if writer is None:
            raise RuntimeError(f"write_video {path}: OpenCV/FFmpeg could not open a writer for any of the codecs "
                               f"{list(fourccs)}")
        try:
            frame = first
            while True:
                writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
                count += 1
                try:
                    frame = _check_rgb_frame(next(it), count, (h, w))
                except StopIteration:
                    break
        finally:
            writer.release()
    return count


def write_frames_png(folder: str | Path, frames: Iterable[np.ndarray]) -> int:
    """Write RGB frames as ``000000.png, 000001.png, ...`` into ``folder``, atomically for the whole folder.

    Args:
        folder: target folder; an existing one is replaced only once every frame has been written.
        frames: iterable of ``(H, W, 3)`` uint8 RGB arrays, all of one size.

    Returns:
        The number of frames written.
    """
    import cv2

    folder = Path(folder)
    count = 0
    size_hw = None
    with atomic_dir(folder) as tmp:
        for frame in frames:
            frame = _check_rgb_frame(frame, count, size_hw)
            size_hw = frame.shape[:2]
            target = tmp / f"{count:06d}.png"
            if not cv2.imwrite(str(target), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)):
                raise OSError(f"write_frames_png: OpenCV could not write {target}")
            count += 1
    return count


# ----------------------------------------------------------------------------------------------- sources


class NativeStderr:
    """What native code (FFmpeg inside OpenCV) writes to the process's stderr during :meth:`capture`, kept
    instead of printed. OpenCV has no hook for FFmpeg's log, so file descriptor 2 points at a temporary file while
    a call runs (nothing of Python's own writes to stderr, tqdm and logging included, runs meanwhile)."""

    _PREFIX = re.compile(r"^\[[^\]]* @ 0x[0-9a-f]+\]\s*")  # "[mpeg4 @ 0x55d0...] " (an address per run)

    def __init__(self) -> None:
        self._file = None
        self._read = 0

    @contextlib.contextmanager
    def capture(self) -> Iterator[None]:
        if self._file is None:
            self._file = tempfile.TemporaryFile()
        for stream in (sys.stdout, sys.stderr):  # what Python buffered goes out first, in order
            with contextlib.suppress(Exception):
                stream.flush()
        saved = os.dup(2)
        try:
            os.dup2(self._file.fileno(), 2)
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)

    def new_lines(self) -> list[str]:
        """The lines written since the last call, without FFmpeg's ``[codec @ address]`` prefix."""
        if self._file is None:
            return []
        size = os.fstat(self._file.fileno()).st_size
        if size == self._read:
            return []
        self._file.seek(self._read)
        text = self._file.read().decode("utf-8", "replace")
        self._read = size
        return [self._PREFIX.sub("", line).strip() for line in text.splitlines() if line.strip()]

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file, self._read = None, 0


def frame_ranges(indices: list[int]) -> str:
    """Sorted frame indices as ranges: ``[3, 4, 5, 9]`` -> ``'3-5, 9'``."""
    out: list[str] = []
    for i in indices:
        if out and int(out[-1].split("-")[-1]) == i - 1:
            out[-1] = f"{out[-1].split('-')[0]}-{i}"
        else:
            out.append(str(i))
    return ", ".join(out)



class VideoSource(abc.ABC):
    """A sequence of RGB frames: a video file or an image folder.

    Attributes:
        path: the file or folder.
        num_frames: number of frames (see the module docstring for video files).
        size_wh: ``(W, H)`` of the decoded frames.
        fps: frame rate from the container, or ``None`` (image folders, or a container without one).
    """

    path: Path
    num_frames: int
    size_wh: tuple[int, int]
    fps: float | None

    def __len__(self) -> int:
        return self.num_frames

    def __enter__(self) -> VideoSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release open files (a closed source re-opens on the next read)."""

    def read(self, start: int = 0, stop: int | None = None, *, strict: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Frames ``start .. stop-1`` (``stop=None``: to the end).

        Returns:
            frames: ``(N, H, W, 3)`` uint8 RGB; invalid frames are zeros.
            valid: ``(N,)`` bool, False where a frame could not be decoded (only when ``strict=False``).

        Raises:
            InputError: a frame could not be decoded and ``strict`` (names the file and the frame index); a range
                outside ``[0, num_frames]``.
        """
        stop = self.num_frames if stop is None else stop
        if not 0 <= start <= stop <= self.num_frames:
            raise InputError(f"{self.path}: frame range [{start}, {stop}) outside [0, {self.num_frames}]")
        return self.read_indices(range(start, stop), strict=strict)

    def read_indices(self, indices: Iterable[int], *, strict: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Frames at increasing ``indices`` (N,), decoded in one forward pass; returns as :meth:`read`."""
        idx = [int(i) for i in indices]
        if any(b <= a for a, b in zip(idx, idx[1:])):
            raise InputError(f"{self.path}: frame indices must be strictly increasing")
        if idx and not (0 <= idx[0] and idx[-1] < self.num_frames):
            raise InputError(f"{self.path}: frame indices {idx[0]}..{idx[-1]} outside [0, {self.num_frames})")
        w, h = self.size_wh
        frames = np.zeros((len(idx), h, w, 3), np.uint8)  # (N, H, W, 3)
        valid = np.zeros(len(idx), bool)  # (N,)
        for k, i in enumerate(idx):
            valid[k] = self._decode_into(i, frames[k])
            if not valid[k] and strict:
                raise InputError(f"{self.path}: frame {i} could not be decoded{self._why(i)}")
        if not valid.all():  # one warning per source (the same text each time), each frame logged at debug level
            bad = [i for i, v in zip(idx, valid) if not v]
            logger.debug("%s: frame(s) %s could not be decoded", self.path, frame_ranges(bad))
            if not getattr(self, "_warned_decode", False):
                self._warned_decode = True
                warnings.warn(f"{self.path}: some frames could not be decoded{self._why(bad[0])}; they are marked "
                              "invalid (-v lists them)", DataWarning, stacklevel=2)
        return frames, valid

    def read_frame(self, index: int) -> np.ndarray:
        """Frame ``index`` as ``(H, W, 3)`` uint8 RGB; ``InputError`` if it does not decode."""
        return self.read(index, index + 1)[0][0]

    @abc.abstractmethod
    def _decode_into(self, index: int, out: np.ndarray) -> bool:
        """Decode frame ``index`` (RGB) into ``out`` (H, W, 3); False if it cannot be decoded."""

    def _why(self, index: int) -> str:
        return ""


class VideoFileSource(VideoSource):
    """A video file decoded sequentially by OpenCV/FFmpeg (see the module docstring).

    Decoded frames are placed by their presentation timestamp, ``round((t - t_0) * fps)``, not by how many
    frames came before: after a damaged stretch FFmpeg drops frames, and counting would shift every later frame
    (measured here: a stream with zeroed bytes delivers frame 11 as the 10th decoded picture). Frames whose
    timestamp never appears are invalid. Without an fps the count is used.

    Args:
        path: the video file.
        verify_frame_count: decode the whole file once to count its frames instead of trusting the container.

    Raises:
        InputError: the file is missing, cannot be opened, or its first frame does not decode.
    """

    #: consecutive decode failures after which the verifying count stops (the end of a damaged stream)
    _MAX_FAILURES = 32

    def __init__(self, path: str | Path, *, verify_frame_count: bool = False) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"video file not found: {self.path}")
        self._cap = None
        self._t0_ms = 0.0
        self._ffmpeg = NativeStderr()
        self._ffmpeg_lines = 0  # FFmpeg lines seen: the first is warned about, the others logged at debug level
        cap = self._open()
        cv2 = self._cv2
        header = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        self.fps = fps if np.isfinite(fps) and fps > 0 else None
        with self._ffmpeg.capture():
            grabbed = cap.grab()
        if not grabbed:
            self.close()
            raise InputError(f"{self.path}: frame 0 could not be decoded (the file opens but holds no readable "
                             f"video frames){self._ffmpeg_says()}")
        self._t0_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
        with self._ffmpeg.capture():
            ok, bgr = cap.retrieve()
        self.close()
        if not ok or bgr is None:
            raise InputError(f"{self.path}: frame 0 could not be decoded{self._ffmpeg_says()}")
        self.size_wh = (int(bgr.shape[1]), int(bgr.shape[0]))
        self.header_frame_count = header
        if verify_frame_count or header <= 0:
            self.num_frames = self._count_decodable()
            if header > 0 and header != self.num_frames:
                warnings.warn(f"{self.path}: the container says {header} frames but {self.num_frames} decode",
                              DataWarning, stacklevel=2)
        else:
            self.num_frames = header
        self._report_ffmpeg()

    @property
    def _cv2(self):
        import cv2

        return cv2

    def __getstate__(self) -> dict:
        """Pickled without its decoder (a worker process re-opens the file on its first read)."""
        state = dict(self.__dict__, _cap=None, _ffmpeg=NativeStderr())
        state.pop("_pos", None)
        state.pop("_held", None)
        return state

    def _open(self):
        self.close()
        with self._ffmpeg.capture():
            cap = self._cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise InputError(f"cannot open video file {self.path}: OpenCV/FFmpeg cannot read it (not a video, "
                             f"truncated, or an unsupported codec){self._ffmpeg_says()}")
        self._cap = cap
        self._pos = 0  # every frame index below _pos is gone (delivered, skipped or lost)
        self._held: int | None = None  # index of a frame grabbed but not yet retrieved (>= _pos)
        return cap

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def _ffmpeg_says(self) -> str:
        """``" (FFmpeg: ...)"`` with what FFmpeg wrote since the last report, for an error message."""
        lines = self._ffmpeg.new_lines()
        self._ffmpeg_lines += len(lines)
        return f" (FFmpeg: {'; '.join(dict.fromkeys(lines))})" if lines else ""

    def _report_ffmpeg(self) -> None:
        """What FFmpeg wrote since the last report: the first time a warning, afterwards debug lines."""
        lines = self._ffmpeg.new_lines()
        if not lines:
            return
        first = self._ffmpeg_lines == 0
        self._ffmpeg_lines += len(lines)
        for line in lines:
            logger.debug("%s: FFmpeg: %s", self.path, line)
        if first:
            warnings.warn(f"{self.path}: FFmpeg reported problems decoding it, such as '{lines[0]}' (-v shows "
                          "FFmpeg's messages)", DataWarning, stacklevel=3)

    def read_indices(self, indices: Iterable[int], *, strict: bool = True) -> tuple[np.ndarray, np.ndarray]:
        try:
            return super().read_indices(indices, strict=strict)
        finally:
            self._report_ffmpeg()

    def _grab(self) -> bool:
        """Decode the next picture; on success hold it at its timestamp index, else count one lost frame."""
        cap = self._cap
        with self._ffmpeg.capture():
            grabbed = cap.grab()
        if not grabbed:
            self._pos += 1
            return False
        index = self._pos
        if self.fps is not None:
            ms = float(cap.get(self._cv2.CAP_PROP_POS_MSEC))
            index = max(int(round((ms - self._t0_ms) * self.fps / 1000.0)), self._pos)
        self._held = self._pos = index
        return True

    def _count_decodable(self) -> int:
        """Decode every frame; the count is the last decodable index + 1."""
        self._open()
        last, failures = -1, 0
        while failures < self._MAX_FAILURES:
            if self._grab():
                last, failures = self._held, 0
                self._held, self._pos = None, last + 1
            else:
                failures += 1
        self.close()
        return last + 1

    def _why(self, index: int) -> str:
        return " (damaged stream, or fewer frames than the container says)"

    def _decode_into(self, index: int, out: np.ndarray) -> bool:
        cv2 = self._cv2
        if self._cap is None or index < self._pos:
            self._open()
        while self._held is None or self._held < index:
            if self._held is not None:  # a frame before the one wanted: drop it
                self._pos, self._held = self._held + 1, None
            if self._pos > index:
                return False  # frame `index` was lost in a failed decode
            self._grab()  # grab only decodes; the colour conversion happens in retrieve
        if self._held > index:
            return False  # the next decodable frame comes after `index`: it is kept for a later call
        with self._ffmpeg.capture():
            ok, bgr = self._cap.retrieve()
        self._pos, self._held = index + 1, None
        if not ok or bgr is None:
            return False
        if bgr.shape != out.shape:
            raise InputError(f"{self.path}: frame {index} decodes as {bgr.shape[1]}x{bgr.shape[0]} (WxH), frame 0 as "
                             f"{out.shape[1]}x{out.shape[0]}: the frame size changes within the video")
        cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB, dst=out)
        return True


def _natural_key(name: str) -> list:
    """Sort key comparing digit runs as numbers: ``frame2.png`` before ``frame10.png``."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def list_images(folder: Path) -> list[Path]:
    """Image files (png/jpg/jpeg, any case, not hidden) in ``folder``, sorted by name (numbers numerically)."""
    files = [p for p in folder.iterdir()
             if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")]
    return sorted(files, key=lambda p: _natural_key(p.name))


class ImageFolderSource(VideoSource):
    """A folder of png/jpg frames, in name order (digit runs compared as numbers).

    Args:
        folder: the folder.
        fps: frame rate to report (an image folder has none of its own).

    Raises:
        InputError: the folder is missing, holds no images, or its first image cannot be read.
    """

    def __init__(self, folder: str | Path, *, fps: float | None = None) -> None:
        self.path = Path(folder)
        if not self.path.is_dir():
            raise InputError(f"image folder not found: {self.path}")
        self.files = list_images(self.path)
        if not self.files:
            raise InputError(f"image folder {self.path} holds no {'/'.join(s[1:] for s in IMAGE_SUFFIXES)} files")
        first = self._imread(self.files[0])
        if first is None:
            raise InputError(f"{self.files[0]}: frame 0 of {self.path} cannot be read as an image")
        self.size_wh = (int(first.shape[1]), int(first.shape[0]))
        self.num_frames = len(self.files)
        self.fps = fps

    @staticmethod
    def _imread(file: Path) -> np.ndarray | None:
        import cv2

        return cv2.imread(str(file), cv2.IMREAD_COLOR)  # BGR (H, W, 3) uint8, or None

    def _why(self, index: int) -> str:
        return f" ({self.files[index].name} is not a readable image)"

    def _decode_into(self, index: int, out: np.ndarray) -> bool:
        import cv2

        bgr = self._imread(self.files[index])
        if bgr is None:
            return False
        if bgr.shape != out.shape:
            raise InputError(f"{self.files[index]}: frame {index} is {bgr.shape[1]}x{bgr.shape[0]} (WxH) but frame 0 "
                             f"of {self.path} is {out.shape[1]}x{out.shape[0]}")
        cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB, dst=out)
        return True


def open_video_source(path: str | Path, *, fps: float | None = None,
                      verify_frame_count: bool = False) -> VideoSource:
    """Open a video file or an image folder as a :class:`VideoSource`.

    Args:
        path: a video file (any container FFmpeg reads) or a folder of png/jpg frames.
        fps: frame rate for an image folder (ignored for video files, which carry their own).
        verify_frame_count: for video files, count frames by decoding (see the module docstring).
    """
    path = Path(path)
    if path.is_dir():
        return ImageFolderSource(path, fps=fps)
    return VideoFileSource(path, verify_frame_count=verify_frame_count)
