"""Track a sequence folder as `torchtrack track` does, in one library call: :func:`track`.

The background (measured from ``background/`` frames or estimated from the video), the observation model, the
start (fitted to detected 2D keypoints on small rigs, else searched in the voxels, or a given pose), the track,
the background refinement, the body refit and the smoothing in time, with the settings of a tracking config
(``configs/markerless.yaml``) and the overrides the CLI has. The CLI and the evaluation scripts call it, so that
what is measured is what users run.

Threads: the tracker is thousands of small tensor operations a frame, which one intra-op thread runs as fast as
several on an idle machine, and which several run many times slower beside a busy process (they wait for each
other). :func:`track` runs with ``threads`` intra-op threads (default 1) and gives an observation worker the
machine's other cores (:func:`~torchtrack.tracking.stream.observe_batches`); ``scripts/bench_busy.py`` measures
both beside a busy process (docs/results.md, "Speed").
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from torchtrack.checks import InputError
from torchtrack.io.poses import Poses

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

#: The built-in tracking config.
DEFAULT_CONFIG = "markerless.yaml"
_SECTIONS = ("observation", "background", "tracker", "keypoint_start", "background_refinement", "body_refit",
             "smoothing")


class NothingTracked(Exception):
    """A track without a single valid frame (nobody found, or every frame refused); ``poses`` holds it."""

    def __init__(self, message: str, poses: Poses) -> None:
        super().__init__(message)
        self.poses = poses


@dataclass(frozen=True)
class TrackResult:
    """What :func:`track` returns.

    Attributes:
        poses: the track (docs/formats.md), smoothed in time as the config says.
        refinement_tracks: the background refinement's tracks (1 without refinement; the kept one, tracked again
            for its logs, counts too).
        refits: per body refit pass, whether it was kept.
        seconds: the call's wall-clock time.
    """

    poses: Poses
    refinement_tracks: int
    refits: tuple[bool, ...]
    seconds: float


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_config(name: str | Path, _seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """The YAML tracking config as a dict with ``observation``, ``background``, ``tracker``,
    ``background_refinement``, ``body_refit`` and ``smoothing`` sections (and ``source``). ``name``: a built-in
    config's name (``markerless_fast``) or a YAML path. A file may start from another with ``extends: NAME`` and
    override some settings."""
    import yaml

    from torchtrack.resources import config_path

    path = config_path(name)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(doc, dict) or set(doc) - {*_SECTIONS, "extends"}:
        raise InputError(f"{path}: expected the sections 'observation', 'background', 'tracker', "
                         "'keypoint_start', 'background_refinement', 'body_refit' and 'smoothing' (and 'extends') "
                         "only")
    if "extends" in doc:
        if str(path) in _seen:
            raise InputError(f"{path}: 'extends' loops back to itself")
        base = load_config(str(doc.pop("extends")), _seen + (str(path),))
        base.pop("source", None)
        doc = _merge(base, doc)
    for section in _SECTIONS:
        doc.setdefault(section, {})
    doc["source"] = str(path)
    return doc


def keypoint_start(folder: Any, config: Any, start: int, stop: int | None) -> Any:
    """The start from detected 2D keypoints (:mod:`torchtrack.keypoints.start`), or None where the config turns it
    off, the detector is not installed (``enabled: auto``) or the start frame shows no consistent person (the
    tracker then searches the voxels)."""
    from torchtrack.keypoints.detector import INSTALL_HINT, detector_available, load_detector
    from torchtrack.keypoints.start import start_from_keypoints
    from torchtrack.skeleton import Skeleton

    if config.enabled == "off":
        return None
    if config.enabled == "auto" and folder.num_cameras > config.max_cameras:
        return None
    if config.enabled == "auto" and not detector_available(config.detector):
        log.info("no keypoint detector installed (%s); the start is searched in the voxels", INSTALL_HINT)
        return None
    detector = load_detector(config.detector)
    try:
        found, why = start_from_keypoints(folder, folder.rig, Skeleton.from_urdf(), detector, config,
                                          start, stop)
    finally:
        detector.close()
    if found is None:
        log.warning("%s: no start from keypoints (%s); the start is searched in the voxels", folder.root, why)
    return found


def _one_person(folder: Any, frame: int, observer: Any, tracker: Any, size_wh: tuple[int, int],
                device: torch.device) -> bool:
    """Whether the keypoint start's frame holds one person in the voxels, as the voxel start requires
    (:meth:`~torchtrack.tracking.markerless.MarkerlessTracker.check_one_person`): the detector sees one person per
    image, and the cameras that agree on one of two would start on them silently. Where it does not, says so and
    the voxel start takes over (it waits for a frame with one person)."""
    fb = next(iter(folder.iter_batches(1, frame, frame + 1, device=device, size_wh=size_wh)))
    try:
        tracker.check_one_person(observer(fb.images, fb.valid)[0])
    except InputError as exc:
        log.warning("%s: the start from keypoints is not used (frame %d: %s); the start is searched in the voxels",
                    folder.root, frame, str(exc).split(". ")[0])
        return False
    return True


def _log_keypoint_start(tb: Any, folder: Any, found: Any, size_wh: tuple[int, int]) -> None:
    """TensorBoard: the start frame's images with the detected keypoints and the body fitted to them
    (``start/keypoints/<camera>``)."""
    import torch

    from torchtrack.keypoints.start import draw_keypoint_start

    rig = folder.rig.resized(*size_wh).float()
    images = torch.nan_to_num(folder.read_frame(found.frame, size_wh=size_wh), nan=0.0)
    tb.camera_images(found.frame, "start/keypoints", draw_keypoint_start(images, rig, found, folder.image_size_wh),
                     rig.names)


def observer_from_config(rig: Any, background: Any, ocfg: dict[str, Any], model: str, voxel_m: float) -> Any:
    """The :class:`~torchtrack.tracking.observation.Observer` of a config's ``observation`` section."""
    from torchtrack.occupancy import BayesConfig, HullConfig
    from torchtrack.tracking.observation import Observer, default_silhouettes

    known = {"model", "voxel_m", "scale", "threshold", "min_views", "bayes", "hull", "fill_static_subject", "workers",
             "silhouettes"}
    unknown = set(ocfg) - known
    if unknown:
        raise InputError(f"observation config: unknown settings {sorted(unknown)}; known: {sorted(known)}")
    try:
        hull = HullConfig(**(ocfg.get("hull") or {}))
    except TypeError as exc:
        raise InputError(f"observation config, hull: {exc}") from None
    bayes_doc = ocfg.get("bayes") or {}
    if "min_views" in bayes_doc:
        raise InputError("observation config, bayes: set min_views in the observation section")
    try:
        bayes = BayesConfig(**bayes_doc)
    except (TypeError, InputError) as exc:
        raise InputError(f"observation config, bayes: {exc}") from None
    silhouettes = ocfg.get("silhouettes", False)
    if silhouettes is None:
        silhouettes = default_silhouettes(model)
    elif not isinstance(silhouettes, bool):
        raise InputError(f"observation config: silhouettes must be true, false or null, got {silhouettes!r}")
    elif silhouettes and model != "bayes":
        silhouettes = False  # the hull keeps no per-pixel evidence: its search scores against the voxels
    return Observer(rig, background, model, voxel_m, threshold=float(ocfg.get("threshold", 0.5)),
                    min_views=ocfg.get("min_views"), bayes=bayes, hull=hull, silhouettes=silhouettes)


def read_start_pose(poses: Poses | str | Path) -> tuple[torch.Tensor, float | None, Any]:
    """The first valid frame's angles ``(D,)`` of a poses file (or :class:`Poses`), its subject height
    (``subject_height_m``) and its subject's body (``body_urdf``: :func:`~torchtrack.tracking.refine.track_body`),
    each None where the file has none."""
    import numpy as np
    import torch

    from torchtrack.io.poses import load_poses
    from torchtrack.tracking.refine import track_body

    source = "the start pose" if isinstance(poses, Poses) else str(poses)
    if not isinstance(poses, Poses):
        poses = load_poses(poses)
    body = track_body(poses, source)  # checks the DOFs of both
    ok = np.flatnonzero(poses.valid)
    if ok.size == 0:
        raise InputError(f"{source}: no valid frame to start from")
    height = poses.extra.get("subject_height_m")
    return torch.as_tensor(poses.angles[ok[0]], dtype=torch.float32), (
        float(height) if height is not None else None), body


@contextlib.contextmanager
def intra_op_threads(threads: int | None) -> Iterator[None]:
    """torch's intra-op threads set to ``threads`` for the block (None: as they are), restored after."""
    import torch

    before = torch.get_num_threads()
    if threads is not None:
        if threads < 1:
            raise InputError(f"threads must be >= 1, got {threads}")
        torch.set_num_threads(int(threads))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def track(seq: str | Path | Any, *, config: str | Path | dict[str, Any] = DEFAULT_CONFIG, model: str | None = None,
          voxel_m: float | None = None, scale: float | None = None, init_pose: Poses | str | Path | None = None,
          height_m: float | None = None, start: int = 0, stop: int | None = None, batch: int = 4,
          device: str | torch.device = "cpu", workers: int | None = 0, fill_static_subject: bool | None = None,
          refine_passes: int | None = None, refit_passes: int | None = None, smooth_hz: float | None = None,
          background_from_track: Poses | str | Path | None = None, background: Any = None, threads: int | None = 1,
          log_dir: str | Path | None = None, log_every: int = 10, progress: bool = True,
          on_pass: Callable[[int, Poses], None] | None = None,
          on_refit: Callable[[int, Poses, bool], None] | None = None, frame_cache_mb: float = 1024) -> TrackResult:
    """Track the sequence folder ``seq`` as `torchtrack track` does (module docstring).

    Args:
        seq: a sequence folder (docs/formats.md) or a :class:`~torchtrack.io.sequence.SequenceFolder`.
        config: a tracking config's name or YAML path, or a config dict as :func:`load_config` returns it.
        model, voxel_m, scale, fill_static_subject, refine_passes, refit_passes, smooth_hz: override the config's
            ``observation.model``, ``observation.voxel_m``, ``observation.scale``,
            ``observation.fill_static_subject``, ``background_refinement.passes``, ``body_refit.passes`` and
            ``smoothing.cutoff_hz`` (None: the config's).
        workers: 1 reads and observes the frames in a worker process ahead of the tracker (the same track,
            faster on a CPU; a calling script then needs an ``if __name__ == "__main__":`` guard, as for any
            spawned process), 0 in this process (the default here), None the config's ``observation.workers``
            (`torchtrack track`'s default: 1).
        init_pose: start from the first valid frame of this poses file (with its body where it has one) instead of
            the automatic start (the config's ``keypoint_start``, else the search in the voxels). height_m: the
            subject's height for an ``init_pose`` without a body (default: its ``subject_height_m``, else
            meta.toml's, else 1.75); with a body, the body scaled to it.
        start, stop: the frames ``[start, stop)`` to track. batch: frames read and observed together.
        device: torch device. threads: intra-op threads of this process while it tracks (None: as they are).
        background_from_track: start from the background re-estimated from this earlier track of ``seq``.
        background: start from this :class:`~torchtrack.background.BackgroundModel` (at the processing size)
            instead of estimating one; refined from the track as an estimated one is, unless it was measured from
            background frames.
        log_dir: TensorBoard logs there (the kept track at its top, each body refit in ``body_refit_N``); None:
            none. log_every: images and the 3D view every N frames (0: never). progress: progress bars.
        on_pass: called with each background refinement pass's number (0 the first track) and its poses, and
            again with the kept pass tracked once more. on_refit: called with each body refit's number (1 the
            first), its poses and whether it was kept. Both for reports; the poses are not smoothed.
        frame_cache_mb: the decoded frames (at the processing size) kept for the passes after the first, in MB,
            in the worker or in this process (0: decoded each pass; the real Pose2Sim demo at ``scale`` 0.25 needs
            157 MB).

    Returns:
        the :class:`TrackResult`.

    Raises:
        InputError: a bad setting or input, naming it. NothingTracked: no frame was tracked.
    """
    import torch

    t0 = time.perf_counter()
    with torch.no_grad(), intra_op_threads(threads):
        return _track(seq, config, model, voxel_m, scale, init_pose, height_m, start, stop, batch, device,
                      workers, fill_static_subject, refine_passes, refit_passes, smooth_hz, background_from_track,
                      background, log_dir, log_every, progress, on_pass, on_refit, frame_cache_mb, t0)


def track_many(seqs: list[str | Path | Any], *, batch_size: int = 16, log_dirs: list[str | Path | None] | None = None,
               threads: int | None = 1, progress: bool = True, **options: Any) -> list[TrackResult | Exception]:
    """Track several sequence folders, each as :func:`track` tracks it alone (its own background, start,
    refinement, body refit and smoothing, with the same ``options``), ``batch_size`` of them at a time in lockstep:
    each sequence's pipeline runs in a thread of its own, and their track passes run together, one batched
    per-frame step for all (:func:`~torchtrack.tracking.run.lockstep_passes`). Sequences of different rigs, image
    sizes and frame rates may go together. A sequence that fails (unreadable, no calibration, nobody tracked)
    comes out as its error while the others finish.

    Args:
        seqs: the sequence folders. batch_size: how many are tracked in lockstep at a time (>= 1).
        log_dirs: per sequence, its TensorBoard folder or None. threads: intra-op threads while tracking (None:
            as they are). progress: one progress bar per batch. options: :func:`track`'s other arguments (its
            ``workers`` are 0: the frames are read and observed in each sequence's thread; ``frame_cache_mb`` is
            shared by the sequences tracked at a time).

    Returns:
        per sequence, its :class:`TrackResult` or the exception it failed with.
    """
    import torch

    from torchtrack.tracking.run import lockstep_passes

    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise InputError(f"the batch size must be a whole number >= 1, got {batch_size!r}")
    log_dirs = [None] * len(seqs) if log_dirs is None else list(log_dirs)
    if len(log_dirs) != len(seqs):
        raise InputError(f"track_many: {len(seqs)} sequences but {len(log_dirs)} log folders")
    for bad in ("workers", "log_dir", "on_pass", "on_refit"):
        if bad in options:
            raise InputError(f"track_many: {bad} is not an option here (see log_dirs; frames are observed in each "
                             "sequence's thread)")
    out: list[TrackResult | Exception] = []
    options["frame_cache_mb"] = options.get("frame_cache_mb", 1024) / min(batch_size, max(len(seqs), 1))
    with torch.no_grad(), intra_op_threads(threads):
        for lo in range(0, len(seqs), batch_size):
            jobs = [lambda s=s, d=d: track(s, log_dir=d, workers=0, threads=None, progress=False, **options)
                    for s, d in zip(seqs[lo:lo + batch_size], log_dirs[lo:lo + batch_size])]
            out.extend(lockstep_passes(jobs, progress))
    return out


def _track(seq, config, model, voxel_m, scale, init_pose, height_m, start, stop, batch, device, workers,
           fill_static_subject, refine_passes, refit_passes, smooth_hz, background_from_track, background, log_dir,
           log_every, progress, on_pass, on_refit, frame_cache_mb, t0) -> TrackResult:
    import torch

    from torchtrack.background import BackgroundConfig, BackgroundModel
    from torchtrack.io.poses import load_poses
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.keypoints.start import KeypointStartConfig
    from torchtrack.logging import RunLogger
    from torchtrack.skeleton import Skeleton
    from torchtrack.tracking.body_refit import BodyRefitConfig, track_with_body_refit
    from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
    from torchtrack.tracking.refine import RefineConfig, background_from_track as refined_from_track
    from torchtrack.tracking.refine import track_with_background_refinement
    from torchtrack.tracking.smoothing import SmoothingConfig, smooth_track
    from torchtrack.tracking.stream import ObservationWorker

    if not frame_cache_mb >= 0:
        raise InputError(f"frame_cache_mb must be >= 0, got {frame_cache_mb}")
    cache_bytes = int(frame_cache_mb * 2 ** 20)
    cfg = config if isinstance(config, dict) else load_config(config)
    source = cfg.get("source", "the tracking config")
    ocfg = dict(cfg["observation"])
    model = model or ocfg.get("model", "bayes")
    voxel_m = float(voxel_m if voxel_m is not None else ocfg.get("voxel_m", 0.03))
    scale = float(scale if scale is not None else ocfg.get("scale", 1.0))
    if not 0.05 <= scale <= 1.0:
        raise InputError(f"scale must be in [0.05, 1], got {scale:g}")
    if not 0.005 <= voxel_m <= 0.2:
        raise InputError(f"the voxel size must be in [0.005, 0.2] m, got {voxel_m:g}")
    tcfg = TrackerConfig.from_dict(cfg["tracker"], source)
    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError("device cuda: no CUDA device is available to PyTorch")
    workers = workers if workers is not None else ocfg.get("workers", 0)
    if workers not in (0, 1):
        raise InputError(f"{source}: observation.workers must be 0 or 1, got {workers!r}")
    rcfg = RefineConfig.from_dict(cfg["background_refinement"], source)
    if refine_passes is not None:
        rcfg = replace(rcfg, passes=refine_passes)
    bcfg = BodyRefitConfig.from_dict(cfg["body_refit"], source)
    if refit_passes is not None:
        bcfg = replace(bcfg, passes=refit_passes)
    scfg = SmoothingConfig.from_dict(cfg["smoothing"], source)
    if smooth_hz is not None:
        scfg = replace(scfg, cutoff_hz=smooth_hz)

    folder = seq if isinstance(seq, SequenceFolder) else SequenceFolder(seq)
    W, H = (int(round(float(v) * scale)) for v in folder.rig.image_size_wh[0])
    rig = folder.rig.resized(W, H).float().to(device)
    fill = bool(fill_static_subject if fill_static_subject is not None else ocfg.get("fill_static_subject", False))
    try:
        bg_config = BackgroundConfig(**{**(cfg.get("background") or {}), "fill_static_subject": fill})
    except TypeError as exc:
        raise InputError(f"{source}, background: {exc}") from None
    if background is not None and background_from_track is not None:
        raise InputError("give a background or a track to re-estimate it from, not both")
    sequence = None  # the frames the background was estimated from, for the refinement
    if background is not None:
        bg = background.to(device)
    elif background_from_track is not None:
        name = "the earlier track" if isinstance(background_from_track, Poses) else str(background_from_track)
        earlier = background_from_track if isinstance(background_from_track, Poses) else load_poses(
            background_from_track)
        bg = refined_from_track(folder, earlier, bg_config, rcfg, (W, H), device, source=name,
                                blob_specs=tcfg.blobs)
    else:
        bg, sequence = BackgroundModel.from_folder_and_frames(folder, bg_config, size_wh=(W, H), device=device,
                                                              progress=progress)
    tracker = MarkerlessTracker(Skeleton.from_urdf().to(device), tcfg)
    found = None
    if init_pose is not None:
        angles, height, body = read_start_pose(init_pose)
        angles = angles.to(device)
        if body is not None and height_m is None:  # the file's own subject (e.g. an earlier run's fitted body)
            tracker.initialize_from_pose(angles, skeleton=body.to(device))
            if refit_passes is None:  # refitted only when asked (body_refit.given_body, refit_passes)
                bcfg = bcfg.for_start(body_given=True)
        else:
            tracker.initialize_from_pose(angles, height_m or height or folder.meta.subject_height_m or 1.75)
    else:
        found = keypoint_start(folder, KeypointStartConfig.from_dict(cfg["keypoint_start"], source), start, stop)
    if not bg.from_moving_sequence and rcfg.passes:
        log.info("%s: the background is measured from its background/ frames, not refined from the track",
                 folder.root)
        rcfg = replace(rcfg, passes=0)
    if not rcfg.passes or start > 0 or (stop is not None and stop < folder.num_frames):
        sequence = None  # the refinement samples other frames than the whole clip's

    def make_observer(background: BackgroundModel) -> Any:
        return observer_from_config(rig, background, ocfg, model, voxel_m).to(device)

    if found is not None and not _one_person(folder, found.frame, make_observer(bg), tracker, (W, H), device):
        found = None
    if found is not None:  # a body fitted to the keypoints of several frames, kept as a given one
        tracker.initialize_from_pose(found.angles.to(device), skeleton=found.skeleton.to(device))
        if refit_passes is None:
            bcfg = bcfg.for_start(body_given=True)

    with contextlib.ExitStack() as stack:
        if workers and device.type == "cpu":  # one worker, and the frames decoded once, for all the passes
            workers = stack.enter_context(ObservationWorker(cache_bytes=cache_bytes))
        elif rcfg.passes or bcfg.passes:
            folder.cache_frames(cache_bytes)
        tb = stack.enter_context(RunLogger(log_dir)) if log_dir is not None else None
        if tb is not None and found is not None:
            _log_keypoint_start(tb, folder, found, (W, H))
        passes: list[int] = []  # the passes run (the refinement may stop early)
        refits: list[bool] = []  # whether each body refit pass was kept

        def pass_done(p: int, q: Poses) -> None:
            passes.append(p)
            if on_pass is not None:
                on_pass(p, q)

        def refit_done(p: int, q: Poses, kept: bool) -> None:
            refits.append(kept)
            if on_refit is not None:
                on_refit(p, q, kept)

        poses, _, bg = track_with_background_refinement(
            folder, bg, make_observer, tracker, rcfg, bg_config, start, stop, batch, device, logger=tb,
            log_every=log_every, progress=progress, workers=workers, on_pass=pass_done, sequence=sequence)
        del sequence  # its frames: not held through the body refit
        kept_pass = poses.extra.get("refinement_pass")  # a kept body refit's track is a new record: carry it over
        refit_logger = None if log_dir is None else lambda p: RunLogger(Path(log_dir) / f"body_refit_{p}")
        poses, _ = track_with_body_refit(
            folder, lambda: make_observer(bg), tracker, poses, bcfg, start, stop, batch, device,
            make_logger=refit_logger, log_every=log_every, progress=progress, workers=workers, on_pass=refit_done)
    if kept_pass is not None:
        poses.extra["refinement_pass"] = kept_pass
    if not poses.valid.any():
        if tracker.subject is not None:
            why = "every frame was refused by the fit checks (see the warnings above)"
        elif tracker.start_refusals:
            why = (f"no frame was one to start from ({len(tracker.start_refusals)} with voxels; the first: "
                   f"{tracker.start_refusals[0]})")
        else:
            why = "nobody was found in the capture volume in any frame"
            if bg.from_moving_sequence:
                why += (" (the background was estimated from the video: a subject who stays in place is in it; "
                        "record empty frames in background/"
                        + (")" if bg_config.fill_static_subject else ", or try --fill-static-subject)"))
        raise NothingTracked(f"none of the {poses.num_frames} frames of {folder.root} was tracked: {why}", poses)
    poses = smooth_track(poses, tracker.subject.skeleton, scfg)
    return TrackResult(poses, len(passes), tuple(refits), time.perf_counter() - t0)
