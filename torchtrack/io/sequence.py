"""Reader for the sequence folder (docs/formats.md).

::

    SEQ/
      calibration.toml            native calibration (read by torchtrack.cameras.load_calibration)
      video/<cam>.mp4             or frames/<cam>/000000.png ...  (png or jpg)
      background/<cam>.mp4        or background/<cam>/*.png: empty scene (optional)
      markers2d.npz, gt.npz       optional
      meta.toml                   optional: fps, subject_height_m, notes

Decisions (documented here because trackers rely on them):

* **Camera names -> files.** A camera's source is the file or folder whose name equals the calibration name;
  failing that, the one whose *normalised* name is equal (lower case, non-alphanumerics removed: ``cam_01``
  matches ``cam01.mp4``, logged at INFO). ``frames/<cam>/`` wins over ``video/<cam>.*`` when both exist (lossless).
  A camera without a source is an ``InputError`` listing what was found; sources without a camera are warned about.
* **Sizes.** Frames are delivered at the *calibrated* size so pixel coordinates match the intrinsics. A decoded
  frame smaller than calibrated by at most ``max_pad_px`` in each dimension (codec padding: the real
  pose2sim_demo cam01/cam02 decode 1080x1920 while calibrated 1088x1920) is padded right/bottom by edge
  replication, with one :class:`~torchtrack.io.video.DataWarning` per camera. Any other mismatch is an
  ``InputError``. ``size_wh`` then resizes (``cv2.INTER_AREA``); the caller scales the intrinsics to match.
* **Frame counts** differing between cameras: a warning naming them; the sequence is as long as the count that
  :func:`min_readable_cameras` of them reach, and a camera is left out (invalid) of the frames it lacks, so one
  camera that ends early costs the others nothing (background frames: the minimum is used).
* **Damaged frames** do not stop a run: batches carry ``valid (B, C)`` and the images of an invalid
  (frame, camera) are NaN, so code that ignores the mask fails loudly instead of tracking on zeros. A file that
  cannot be opened at all is an ``InputError`` when the folder is opened.
"""

from __future__ import annotations

import logging
import math
import re
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from torchtrack.checks import InputError, check_shape
from torchtrack.io.video import VIDEO_SUFFIXES, DataWarning, VideoFileSource, VideoSource, open_video_source

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

logger = logging.getLogger(__name__)


def evenly_spaced(count: int, max_count: int) -> list[int]:
    """At most ``max_count`` indices into ``range(count)``, evenly spaced, first and last included (rounded to
    the nearest index, duplicates dropped)."""
    if max_count < 1:
        raise InputError(f"max_frames must be >= 1, got {max_count}")
    return sorted({int(i) for i in np.linspace(0, count - 1, min(max_count, count)).round()})


#: Frames decoded per block by :meth:`SequenceFolder.sample_frames` (bounds the full-size decode buffers).
SAMPLE_CHUNK = 8

#: Frame rate assumed when neither meta.toml nor the videos give one.
DEFAULT_FPS = 30.0
#: Largest codec padding (pixels per dimension) accepted between decoded and calibrated frame sizes.
MAX_PAD_PX = 16


# ----------------------------------------------------------------------------------------------- meta.toml


@dataclass(frozen=True)
class SequenceMeta:
    """Contents of ``meta.toml``; every field is optional.

    Attributes:
        fps: frame rate, or None (then taken from the videos).
        subject_height_m: the subject's standing height in metres, or None (unknown).
        notes: free text.
        extra: any other top-level keys, as read.
    """

    fps: float | None = None
    subject_height_m: float | None = None
    notes: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


def _positive(value: Any, key: str, path: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise InputError(f"{path}: '{key}' must be a positive number, got {value!r}")
    return float(value)


def read_meta(path: str | Path) -> SequenceMeta:
    """Read ``meta.toml``; a missing file gives the defaults.

    Keys: ``fps``, ``subject_height_m`` (``subject_height`` is accepted as an alias), ``notes``; others go to
    ``extra``. Raises ``InputError`` naming the file for bad TOML or a non-positive number.
    """
    path = Path(path)
    if not path.exists():
        return SequenceMeta()
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid TOML: {e}") from e
    if "subject_height_m" in data and "subject_height" in data:
        raise InputError(f"{path}: give 'subject_height_m' or its alias 'subject_height', not both")
    fps = data.pop("fps", None)
    height = data.pop("subject_height_m", data.pop("subject_height", None))
    notes = data.pop("notes", "")
    return SequenceMeta(fps=None if fps is None else _positive(fps, "fps", path),
                        subject_height_m=None if height is None else _positive(height, "subject_height_m", path),
                        notes=str(notes), extra=data)


# ----------------------------------------------------------------------------------------------- name matching


def normalise_camera_name(name: str) -> str:
    """Lower case with non-alphanumerics removed: ``'Cam_01'`` -> ``'cam01'``."""
    return re.sub(r"[^0-9a-z]", "", name.lower())


def _scan(folder: Path) -> dict[str, Path]:
    """Name -> source in ``folder``: video files by stem, image sub-folders by name (hidden entries skipped)."""
    found: dict[str, Path] = {}
    if not folder.is_dir():
        return found
    for p in sorted(folder.iterdir()):
        if p.name.startswith("."):
            continue  # hidden files, and the temporaries of atomic writes
        if (p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES) or p.is_dir():
            name = p.stem if p.is_file() else p.name
            if name in found:
                raise InputError(f"{folder}: two sources named '{name}': {found[name].name} and {p.name}")
            found[name] = p
    return found


def _sequence_sources(root: Path) -> dict[str, Path]:
    """Sources of ``root/video`` and ``root/frames``; an image folder wins over a video of the same name."""
    found = _scan(root / "video")
    for name, p in _scan(root / "frames").items():
        if name in found:
            logger.info("camera source '%s': using lossless %s rather than %s", name, p, found[name])
        found[name] = p
    return found


def match_cameras(camera_names: list[str], found: dict[str, Path], where: str) -> tuple[list[Path], list[Path]]:
    """Assign a source to each camera: exact name first, then normalised name.

    Args:
        camera_names: (C,) calibration names.
        found: source name -> path.
        where: folder description for messages.

    Returns:
        (C,) paths in camera order, and the sources no camera claimed.

    Raises:
        InputError: a camera without a source (naming it, ``where`` and what was found), or an ambiguous match.
    """
    free = dict(found)
    chosen: dict[str, Path] = {}
    for cam in camera_names:
        if cam in free:
            chosen[cam] = free.pop(cam)
    for cam in camera_names:
        if cam in chosen:
            continue
        key = normalise_camera_name(cam)
        hits = [n for n in free if normalise_camera_name(n) == key]
        if len(hits) > 1:
            raise InputError(f"camera '{cam}': several sources in {where} match its normalised name '{key}': "
                             f"{sorted(hits)}")
        if not hits:
            listing = ", ".join(str(p.relative_to(p.parent.parent)) for p in found.values()) or "nothing"
            raise InputError(f"camera '{cam}' of the calibration has no frames in {where}: looked for a video "
                             f"'{cam}.<{'|'.join(s[1:] for s in VIDEO_SUFFIXES)}>' or an image folder '{cam}/' "
                             f"(or a name equal to '{key}' after lower-casing and removing non-alphanumerics); "
                             f"found: {listing}")
        logger.info("camera '%s' matched to %s by normalised name '%s'", cam, free[hits[0]], key)
        chosen[cam] = free.pop(hits[0])
    return [chosen[c] for c in camera_names], list(free.values())


# ----------------------------------------------------------------------------------------------- the reader


class FrameBatch(NamedTuple):
    """One batch from :meth:`SequenceFolder.iter_batches`.

    Attributes:
        frame_index: (B,) int64 frame numbers.
        images: (B, C, 3, H, W) float32 RGB in [0, 1]; NaN where ``valid`` is False.
        valid: (B, C) bool, False where a camera's frame could not be decoded.
    """

    frame_index: torch.Tensor
    images: torch.Tensor
    valid: torch.Tensor


def _rig_sizes(rig: Any) -> tuple[list[str], np.ndarray]:
    names = [str(n) for n in rig.names]
    size = torch.as_tensor(rig.image_size_wh).detach().cpu()
    check_shape(size, (len(names), 2), "rig.image_size_wh")
    return names, np.rint(size.double().numpy()).astype(np.int64)  # (C, 2) [W, H]


def min_readable_cameras(num_cameras: int) -> int:
    """Readable cameras a frame needs to be tracked: half the rig (rounded up), at least 3 (a hull carved by
    fewer views is too fat and ghost-ridden to fit), at most all of them."""
    return min(num_cameras, max(3, -(-num_cameras // 2)))


def _bar(label: str | None, total: int):
    """A tqdm progress bar over ``total`` frames labelled ``label``, or a disabled one for None."""
    from tqdm import tqdm

    return tqdm(total=total, desc=label, unit="frame", disable=label is None, leave=False)


def _read_available(src: VideoSource, indices: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`VideoSource.read_indices` (not strict) of the ``indices`` the source has; those past its end come
    back invalid (zeros), without a warning (the folder named the short camera when it opened)."""
    have = [i for i in indices if i < src.num_frames]
    if len(have) == len(indices):
        return src.read_indices(indices, strict=False)
    w, h = src.size_wh
    frames = np.zeros((len(indices), h, w, 3), np.uint8)
    valid = np.zeros(len(indices), bool)
    if have:
        frames[:len(have)], valid[:len(have)] = src.read_indices(have, strict=False)
    return frames, valid


class _FrameCache:
    """Decoded frames by (index, size): (C, H, W, 3) uint8 and (C,) bool each, filled until ``max_bytes``."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes, self.bytes = max_bytes, 0
        self.frames: dict[tuple[int, tuple[int, int] | None], tuple[np.ndarray, np.ndarray]] = {}

    def put(self, key: tuple[int, tuple[int, int] | None], frame: np.ndarray, valid: np.ndarray) -> None:
        if self.bytes + frame.nbytes <= self.max_bytes:
            self.frames[key] = (frame.copy(), valid.copy())  # not a view that keeps a whole batch alive
            self.bytes += frame.nbytes


class SequenceFolder:
    """A sequence folder: calibration, per-camera frame sources, optional background, meta and npz files.

    Args:
        root: the sequence folder.
        rig: a ``CameraRig`` (only ``names`` and ``image_size_wh`` (C, 2) [W, H] are used); None loads
            ``root/calibration.toml`` with ``torchtrack.cameras.load_calibration``.
        verify_frame_count: count video frames by decoding them at open time (slow for long videos).
        max_pad_px: largest decoded-vs-calibrated shortfall per dimension that is padded instead of refused.

    Attributes:
        root, rig, meta (:class:`SequenceMeta`), camera_names (C,), sources (C,) :class:`VideoSource`,
        background_sources (C,) or None, image_size_wh (C, 2) int64 numpy [W, H] calibrated sizes,
        num_frames, fps, gt_path / markers2d_path (None when absent), reported (a set of keys of the problems
        already warned about, so that a run's several passes over the frames warn once).

    A run that reads the frames several times (background refinement, body refit) can keep them decoded:
    :meth:`cache_frames`.

    Raises:
        InputError: missing calibration or camera frames, unreadable files, sizes that do not fit the calibration.
    """

    def __init__(self, root: str | Path, rig: Any = None, *, verify_frame_count: bool = False,
                 max_pad_px: int = MAX_PAD_PX) -> None:
        self.root = Path(root)
        self.reported: set[str] = set()
        self._cache: _FrameCache | None = None
        if not self.root.is_dir():
            raise InputError(f"sequence folder not found: {self.root}")
        if rig is None:
            calib = self.root / "calibration.toml"
            if not calib.is_file():
                raise InputError(f"sequence folder {self.root} has no calibration.toml (and no rig was given)")
            from torchtrack.cameras import load_calibration
            from torchtrack.cameras.calib_io import check_translation_units

            rig = load_calibration(calib, warn_units=False)
            check_translation_units(rig, str(calib))  # metres or refused: a body is tracked in metres
        self.rig = rig
        self.camera_names, self.image_size_wh = _rig_sizes(rig)
        self.max_pad_px = int(max_pad_px)
        self.meta = read_meta(self.root / "meta.toml")

        found = _sequence_sources(self.root)
        paths, extra = match_cameras(self.camera_names, found, f"{self.root}/video or {self.root}/frames")
        if extra:
            warnings.warn(f"{self.root}: sources without a calibrated camera are ignored: "
                          f"{[str(p.relative_to(self.root)) for p in extra]}", DataWarning, stacklevel=2)
        self.sources = self._open_sources(paths, verify_frame_count)
        self.num_frames = self._sequence_count(self.sources)
        self.fps = self._resolve_fps()
        self.background_sources = self._open_background(verify_frame_count)
        self.gt_path = self._optional("gt.npz")
        self.markers2d_path = self._optional("markers2d.npz")

    # ---- opening

    def _optional(self, name: str) -> Path | None:
        p = self.root / name
        return p if p.is_file() else None

    def _open_sources(self, paths: list[Path], verify: bool) -> list[VideoSource]:
        sources = [open_video_source(p, fps=self.meta.fps, verify_frame_count=verify) for p in paths]
        for cam, src, size in zip(self.camera_names, sources, self.image_size_wh):
            self._check_size(cam, src, (int(size[0]), int(size[1])))
        return sources

    def _check_size(self, cam: str, src: VideoSource, calib_wh: tuple[int, int]) -> None:
        (w, h), (cw, ch) = src.size_wh, calib_wh
        if (w, h) == (cw, ch):
            return
        sizes = f"decoded {w}x{h}, calibrated {cw}x{ch} (WxH)"
        if 0 <= cw - w <= self.max_pad_px and 0 <= ch - h <= self.max_pad_px:
            warnings.warn(f"camera '{cam}': {src.path} {sizes}; padding right/bottom by edge replication "
                          f"(codec padding?) so pixel coordinates stay those of the calibration", DataWarning,
                          stacklevel=3)
            return
        raise InputError(f"camera '{cam}': {src.path} {sizes}: the frames do not fit the calibration (only a "
                         f"shortfall of up to {self.max_pad_px} px per dimension is padded)")

    def _sequence_count(self, sources: list[VideoSource]) -> int:
        """The count that enough cameras to track a frame reach (:func:`min_readable_cameras`); each camera that
        has fewer or more frames is named."""
        counts = [s.num_frames for s in sources]
        n = sorted(counts, reverse=True)[min_readable_cameras(len(counts)) - 1]
        odd = [(c, k) for c, k in zip(self.camera_names, counts) if k != n]
        if odd:
            listing = ", ".join(f"'{c}' has {k}" + (f" (left out of frames {k}-{n - 1})" if k < n else
                                                     f" (its last {k - n} unused)") for c, k in odd)
            warnings.warn(f"{self.root}: cameras have different frame counts: the sequence has {n} frames; "
                          f"{listing}", DataWarning, stacklevel=3)
        return n

    def _common_count(self, sources: list[VideoSource], what: str) -> int:
        counts = [s.num_frames for s in sources]
        if len(set(counts)) > 1:
            listing = ", ".join(f"{c}: {n}" for c, n in zip(self.camera_names, counts))
            warnings.warn(f"{self.root}: cameras have different {what} counts ({listing}); using the minimum "
                          f"{min(counts)}", DataWarning, stacklevel=3)
        return min(counts)

    def _resolve_fps(self) -> float:
        video_fps = {round(s.fps, 6) for s in self.sources if isinstance(s, VideoFileSource) and s.fps is not None}
        if self.meta.fps is not None:
            if any(abs(f - self.meta.fps) > 1e-3 * self.meta.fps for f in video_fps):
                warnings.warn(f"{self.root}: meta.toml fps {self.meta.fps} differs from the videos' {sorted(video_fps)}"
                              "; using meta.toml", DataWarning, stacklevel=3)
            return self.meta.fps
        if len(video_fps) > 1:
            warnings.warn(f"{self.root}: videos have different fps {sorted(video_fps)}; using the first camera's",
                          DataWarning, stacklevel=3)
        for s in self.sources:
            if s.fps is not None:
                return float(s.fps)
        warnings.warn(f"{self.root}: no fps in meta.toml or the frame sources; assuming {DEFAULT_FPS}",
                      DataWarning, stacklevel=3)
        return DEFAULT_FPS

    def _open_background(self, verify: bool) -> list[VideoSource] | None:
        folder = self.root / "background"
        if not folder.is_dir():
            return None
        found = _scan(folder)
        try:
            paths, extra = match_cameras(self.camera_names, found, str(folder))
        except InputError as e:
            warnings.warn(f"{e}; ignoring {folder} (the background will have to be estimated)", DataWarning,
                          stacklevel=3)
            return None
        if extra:
            warnings.warn(f"{folder}: sources without a calibrated camera are ignored: {[p.name for p in extra]}",
                          DataWarning, stacklevel=3)
        return self._open_sources(paths, verify)

    # ---- reading

    def cache_frames(self, max_bytes: int) -> None:
        """Keep the frames read from now on, decoded and resized (uint8, at each size asked for), for later reads,
        up to ``max_bytes`` in all (frames beyond it are decoded each time); 0 drops the cache. Frames are the
        same bytes either way: a video is decoded deterministically. Not carried when the folder is pickled."""
        if max_bytes < 0:
            raise InputError(f"cache_frames: max_bytes must be >= 0, got {max_bytes}")
        self._cache = _FrameCache(int(max_bytes)) if max_bytes else None

    @property
    def cached_bytes(self) -> int:
        """The bytes of decoded frames held by :meth:`cache_frames` (0: none)."""
        return 0 if self._cache is None else self._cache.bytes

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_cache": None}  # a worker process gets the sources, not the frames

    def __len__(self) -> int:
        return self.num_frames

    @property
    def num_cameras(self) -> int:
        return len(self.camera_names)

    @property
    def has_background(self) -> bool:
        return self.background_sources is not None

    def _to_images(self, buf: np.ndarray, valid: np.ndarray, device: torch.device | str | None) -> torch.Tensor:
        """(B, C, H, W, 3) uint8 and (B, C) bool -> (B, C, 3, H, W) float32 in [0, 1], NaN where invalid."""
        x = torch.from_numpy(buf)
        if device is not None:
            x = x.to(device)  # move uint8: a quarter of the bytes of float32
        B, C, H, W, _ = x.shape
        images = torch.empty((B, C, 3, H, W), dtype=torch.float32, device=x.device)
        images.copy_(x.permute(0, 1, 4, 2, 3)).div_(255.0)  # one strided pass, then in place
        if not valid.all():
            images[torch.from_numpy(~valid).to(images.device)] = float("nan")
        return images

    def _read_block(self, sources: list[VideoSource], indices: list[int],
                    size_wh: tuple[int, int] | None) -> tuple[np.ndarray, np.ndarray]:
        """Decode ``indices`` (B,) from every camera: (B, C, H, W, 3) uint8 at the output size, (B, C) bool;
        the sequence's frames through the cache where there is one."""
        cache = self._cache if sources is self.sources else None
        if cache is None:
            return self._decode_block(sources, indices, size_wh)
        missing = [i for i in indices if (i, size_wh) not in cache.frames]
        if missing:
            buf, valid = self._decode_block(sources, missing, size_wh)
            for k, i in enumerate(missing):
                cache.put((i, size_wh), buf[k], valid[k])
            if len(missing) == len(indices):
                return buf, valid
            got = dict(zip(missing, zip(buf, valid)))
        else:
            got = {}
        rows = [got.get(i) or cache.frames[i, size_wh] for i in indices]
        return np.stack([r[0] for r in rows]), np.stack([r[1] for r in rows])

    def _decode_block(self, sources: list[VideoSource], indices: list[int],
                      size_wh: tuple[int, int] | None) -> tuple[np.ndarray, np.ndarray]:
        """Decode ``indices`` (B,) from every camera: (B, C, H, W, 3) uint8 at the output size, (B, C) bool."""
        import cv2

        buf = valid = None
        for c, src in enumerate(sources):
            frames, ok = _read_available(src, indices)  # (B, h, w, 3), (B,)
            h, w = frames.shape[1:3]
            cw, ch = (int(v) for v in self.image_size_wh[c])
            out_w, out_h = size_wh if size_wh is not None else (cw, ch)
            if buf is None:
                buf = np.empty((len(indices), len(sources), out_h, out_w, 3), np.uint8)  # (B, C, H, W, 3)
                valid = np.empty((len(indices), len(sources)), bool)  # (B, C)
            elif buf.shape[2:4] != (out_h, out_w):
                raise InputError(f"cameras '{self.camera_names[0]}' and '{self.camera_names[c]}' have different "
                                 "calibrated sizes: pass size_wh to get one batch tensor")
            valid[:, c] = ok
            if (out_w, out_h) == (cw, ch):  # pad codec shortfall (accepted in _check_size) by edge replication
                buf[:, c, :h, :w] = frames
                buf[:, c, :h, w:] = frames[:, :, w - 1:w]
                buf[:, c, h:] = buf[:, c, h - 1:h]
                continue
            for b, f in enumerate(frames):
                if (h, w) != (ch, cw):
                    f = cv2.copyMakeBorder(f, 0, ch - h, 0, cw - w, cv2.BORDER_REPLICATE)
                buf[:, c][b] = cv2.resize(f, (out_w, out_h), interpolation=cv2.INTER_AREA)
        return buf, valid

    def iter_batches(self, batch_size: int, start: int = 0, stop: int | None = None,
                     device: torch.device | str | None = None,
                     size_wh: tuple[int, int] | None = None, step: int = 1) -> Iterator[FrameBatch]:
        """Yield frames ``start, start + step, ..`` before ``stop`` in order, ``batch_size`` at a time (the last batch
        may be shorter).

        At most ``batch_size`` frames per camera are decoded and held at a time.

        Args:
            batch_size: B.
            start, stop: frame range (``stop=None``: to the end).
            device: where the tensors go (None: CPU, where decoding happens).
            size_wh: (W, H) to resize to with ``cv2.INTER_AREA``; None keeps the calibrated size (all cameras
                must then share it).
            step: every ``step``-th frame (the frames between are decoded, not returned).

        Yields:
            :class:`FrameBatch`: frame_index (B,), images (B, C, 3, H, W) float32 RGB [0, 1] (NaN where invalid),
            valid (B, C) bool.
        """
        if batch_size < 1 or step < 1:
            raise InputError(f"batch_size and step must be >= 1, got {batch_size} and {step}")
        stop = self.num_frames if stop is None else stop
        if not 0 <= start <= stop <= self.num_frames:
            raise InputError(f"{self.root}: frame range [{start}, {stop}) outside [0, {self.num_frames}]")
        frames = range(start, stop, step)
        for b0 in range(0, len(frames), batch_size):
            indices = list(frames[b0:b0 + batch_size])
            buf, valid = self._read_block(self.sources, indices, size_wh)
            images = self._to_images(buf, valid, device)
            yield FrameBatch(torch.tensor(indices, dtype=torch.int64, device=images.device), images,
                             torch.from_numpy(valid).to(images.device))

    def read_frames(self, indices: Sequence[int], device: torch.device | str | None = None,
                    size_wh: tuple[int, int] | None = None) -> FrameBatch:
        """The frames ``indices`` (sorted, distinct: each camera decodes them in one forward sweep) of every
        camera, as one batch (all held at once): frame_index (B,), images (B, C, 3, H, W) float32 RGB [0, 1]
        (NaN where invalid), valid (B, C) bool."""
        indices = [int(i) for i in indices]
        if not indices or any(b <= a for a, b in zip(indices, indices[1:])):
            raise InputError(f"{self.root}: read_frames wants sorted, distinct frame indices, got {indices}")
        if indices[0] < 0 or indices[-1] >= self.num_frames:
            raise InputError(f"{self.root}: frames {indices} outside [0, {self.num_frames})")
        buf, valid = self._read_block(self.sources, indices, size_wh)
        images = self._to_images(buf, valid, device)
        return FrameBatch(torch.tensor(indices, dtype=torch.int64, device=images.device), images,
                          torch.from_numpy(valid).to(images.device))

    def read_camera_frames(self, camera: int, indices: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Frames ``indices`` (sorted, distinct) of camera ``camera`` as decoded, at its calibrated size (a codec's
        shortfall padded by edge replication): (B, H, W, 3) uint8 RGB and (B,) bool, False where not decoded."""
        indices = [int(i) for i in indices]
        if not indices or any(b <= a for a, b in zip(indices, indices[1:])) or indices[0] < 0:
            raise InputError(f"{self.root}: read_camera_frames wants sorted, distinct frame indices, got {indices}")
        frames, ok = _read_available(self.sources[camera], indices)
        cw, ch = (int(v) for v in self.image_size_wh[camera])
        h, w = frames.shape[1:3]
        if (h, w) != (ch, cw):
            frames = np.pad(frames, ((0, 0), (0, ch - h), (0, cw - w), (0, 0)), mode="edge")
        return frames, ok

    def read_frame(self, index: int, device: torch.device | str | None = None,
                   size_wh: tuple[int, int] | None = None) -> torch.Tensor:
        """Frame ``index`` of every camera: (C, 3, H, W) float32 RGB [0, 1]; NaN for a camera that fails to decode."""
        if not 0 <= index < self.num_frames:
            raise InputError(f"{self.root}: frame {index} outside [0, {self.num_frames})")
        return next(self.iter_batches(1, index, index + 1, device=device, size_wh=size_wh)).images[0]

    def sample_frames(self, max_frames: int, start: int = 0, stop: int | None = None,
                      device: torch.device | str | None = None, size_wh: tuple[int, int] | None = None,
                      progress: str | None = None) -> tuple[list[int], torch.Tensor]:
        """Up to ``max_frames`` video frames evenly spaced over ``[start, stop)``, first and last included;
        ``progress``: the label of a progress bar over them (None: no bar).

        Returns:
            the frame indices and (N, C, 3, H, W) float16 RGB [0, 1] (half the memory of float32; 1/255 steps
            survive it), NaN for a camera that fails to decode.
        """
        stop = self.num_frames if stop is None else min(stop, self.num_frames)
        if not 0 <= start < stop:
            raise InputError(f"{self.root}: no frames in [{start}, {stop}) ({self.num_frames} frames)")
        indices = [start + i for i in evenly_spaced(stop - start, max_frames)]
        chunks = []
        with _bar(progress, len(indices)) as bar:
            for k in range(0, len(indices), SAMPLE_CHUNK):  # sorted indices: each source decodes forwards
                buf, valid = self._read_block(self.sources, indices[k:k + SAMPLE_CHUNK], size_wh)
                chunks.append(self._to_images(buf, valid, device).half())
                bar.update(len(buf))
        return indices, torch.cat(chunks)

    def background_frames(self, max_frames: int, device: torch.device | str | None = None,
                          size_wh: tuple[int, int] | None = None, progress: str | None = None
                          ) -> torch.Tensor | None:
        """Up to ``max_frames`` empty-scene frames, evenly spaced over the background sources (``progress``: as
        :meth:`sample_frames`).

        Frames where any camera fails to decode are dropped (with a warning).

        Returns:
            (N, C, 3, H, W) float32 RGB [0, 1], N <= max_frames; None without a usable background folder.
        """
        if self.background_sources is None:
            return None
        count = self._common_count(self.background_sources, "background frame")
        indices = evenly_spaced(count, max_frames)  # raises on max_frames < 1
        blocks = []
        with _bar(progress, len(indices)) as bar:
            for k in range(0, len(indices), SAMPLE_CHUNK):
                blocks.append(self._read_block(self.background_sources, indices[k:k + SAMPLE_CHUNK], size_wh))
                bar.update(len(blocks[-1][0]))
        buf, valid = (np.concatenate(parts) for parts in zip(*blocks))
        keep = valid.all(axis=1)  # (N,)
        if not keep.all():
            warnings.warn(f"{self.root}/background: dropped {int((~keep).sum())} frame(s) that did not decode in "
                          "every camera", DataWarning, stacklevel=2)
        if not keep.any():
            return None
        return self._to_images(np.ascontiguousarray(buf[keep]), valid[keep], device)

    # ---- optional files

    @staticmethod
    def _load_npz(path: Path | None) -> dict[str, np.ndarray] | None:
        if path is None:
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except Exception as e:  # zipfile/ValueError/OSError: report the file whatever numpy raised
            raise InputError(f"{path}: cannot read as .npz: {e}") from e

    def load_gt(self) -> dict[str, np.ndarray] | None:
        """Arrays of ``gt.npz`` (the poses.npz schema), or None when absent."""
        return self._load_npz(self.gt_path)

    def load_markers2d(self) -> dict[str, np.ndarray] | None:
        """Arrays of ``markers2d.npz``, or None when absent."""
        return self._load_npz(self.markers2d_path)

    def close(self) -> None:
        """Release the open video files."""
        for s in self.sources + (self.background_sources or []):
            s.close()

    def __enter__(self) -> SequenceFolder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"SequenceFolder({str(self.root)!r}, cameras={self.camera_names}, frames={self.num_frames}, "
                f"fps={self.fps}, background={self.has_background})")
