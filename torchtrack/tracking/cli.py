"""`torchtrack track`: markerless tracking of a sequence folder into ``poses.npz`` with TensorBoard logs."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

DEFAULT_CONFIG = "markerless.yaml"


def _shipped_config() -> dict[str, Any] | None:
    """The built-in ``configs/markerless.yaml`` (not one of that name in the working directory), for the
    defaults the help quotes; None where it cannot be read (the help then names the settings only)."""
    from torchtrack.resources import builtin_config

    try:
        return load_config(str(builtin_config(DEFAULT_CONFIG)))
    except Exception:  # noqa: BLE001 - the help must build whatever the config's state
        return None


def _config_default(cfg: dict[str, Any] | None, key: str) -> str:
    """The help's note on an option that overrides the config's ``SECTION.NAME`` ``key``: "default from
    --config: KEY, VALUE in markerless.yaml" (VALUE in YAML spelling), read from the shipped config."""
    section, name = key.split(".")
    value = (cfg or {}).get(section, {}).get(name)
    if value is None:
        return f"default from --config: {key}"
    text = ("true" if value else "false") if isinstance(value, bool) else (
        f"{value:g}" if isinstance(value, float) else str(value))
    return f"default from --config: {key}, {text} in {DEFAULT_CONFIG}".replace("%", "%%")


def add_parser(sub: argparse._SubParsersAction) -> None:
    from torchtrack.resources import builtin_configs

    cfg = _shipped_config()

    def conf(key: str) -> str:
        return _config_default(cfg, key)

    p = sub.add_parser(
        "track", help="markerless 3D body tracking of a sequence folder",
        description="Track the body through a sequence folder from its occupancy (Bayesian grid or colour hull), "
                    "with blobs fitted by EM, joint goals and CCD inverse kinematics. Writes OUT/poses.npz "
                    "(docs/formats.md) and TensorBoard logs in OUT/tb. The sequence should start with the "
                    "subject in the starfish pose, or give --init-pose. Options marked 'default from --config' "
                    "override that setting of the tracking config.")
    p.add_argument("seq", type=Path, metavar="SEQ",
                   help="sequence folder (calibration.toml, video/ or frames/, background/)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="output folder: new, empty, or an earlier track's (with --overwrite)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier track in DIR (its poses.npz and TensorBoard logs; other files are "
                        "never replaced: such a DIR is refused) (default: refuse)")
    p.add_argument("--config", default=DEFAULT_CONFIG, metavar="NAME",
                   help=f"tracking config: a built-in name ({', '.join(builtin_configs())}) or a YAML path "
                        "(default: %(default)s)")
    p.add_argument("--model", choices=("bayes", "hull"), default=None,
                   help=f"observation model: Bayesian occupancy grid or colour hull ({conf('observation.model')})")
    p.add_argument("--voxel", type=float, default=None, metavar="M",
                   help=f"voxel size in metres, the hull's finest level ({conf('observation.voxel_m')})")
    p.add_argument("--scale", type=float, default=None, metavar="F",
                   help=f"process the images at this fraction of their size, in [0.05, 1] "
                        f"({conf('observation.scale')})")
    p.add_argument("--init-pose", type=Path, default=None, metavar="POSES",
                   help="poses.npz whose first valid frame is the initial pose (an earlier run's, or `torchtrack "
                        "init-pose`'s), with its body where the file has one (default: the starfish start)")
    p.add_argument("--height", type=float, default=None, metavar="M",
                   help="with --init-pose: subject height in metres, the body model scaled to it instead of the "
                        "file's body (default: the file's body, else its height, else meta.toml's, else 1.75)")
    p.add_argument("--start", type=int, default=0, metavar="FRAME",
                   help="first frame to track, a 0-based frame index (default: %(default)s)")
    p.add_argument("--stop", type=int, default=None, metavar="FRAME",
                   help="frame index to stop before, exclusive (default: the end of the sequence)")
    p.add_argument("--batch", type=int, default=4, metavar="N",
                   help="frames read and observed per batch (default: %(default)s)")
    p.add_argument("--log-every", type=int, default=10, metavar="N",
                   help="log images and the 3D view every N frames (0: never) (default: %(default)s)")
    p.add_argument("--device", default="cpu", help="torch device: cpu or cuda (default: %(default)s)")
    p.add_argument("--workers", type=int, choices=(0, 1), default=None,
                   help=f"1: read and observe frames in a worker process ahead of the tracker (CPU); 0: in this "
                        f"process ({conf('observation.workers')})")
    p.add_argument("--fill-static-subject", action="store_true", default=None,
                   help=f"without background/ frames: paint the parts of the subject that never move out of the "
                        f"estimated background, for a subject balancing in place "
                        f"({conf('observation.fill_static_subject')})")
    p.add_argument("--refine-passes", type=int, default=None, metavar="N",
                   help=f"without background/ frames: re-estimate the background from the track and track again, "
                        f"at most N times, background_refinement.keep choosing the result (0: off; "
                        f"{conf('background_refinement.passes')})")
    p.add_argument("--refit-passes", type=int, default=None, metavar="N",
                   help=f"refit the body on several tracked frames and track again, at most N times, each pass "
                        f"kept while it fits better; also refits a body given by --init-pose (0: off; "
                        f"{conf('body_refit.passes')})")
    p.add_argument("--smooth-hz", type=float, default=None, metavar="HZ",
                   help=f"low-pass cut-off in Hz for the finished track's joint angles, zero-phase Butterworth "
                        f"(0: off; {conf('smoothing.cutoff_hz')})")
    p.add_argument("--background-from-track", type=Path, default=None, metavar="POSES",
                   help="start from the background re-estimated from an earlier track of SEQ, its poses.npz (with "
                        "--init-pose POSES and --refine-passes 0: about one more refinement pass of that run) "
                        "(default: from background/, else estimated from the video)")
    p.set_defaults(func=run)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_config(name: str, _seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """The YAML tracking config as a dict with ``observation``, ``tracker``, ``background_refinement``,
    ``body_refit`` and ``smoothing`` sections (and ``source``).

    A file may start from another with ``extends: NAME`` and override some settings.
    """
    import yaml

    from torchtrack.checks import InputError
    from torchtrack.resources import config_path

    path = config_path(name)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(doc, dict) or set(doc) - {"observation", "tracker", "background_refinement", "body_refit",
                                                 "smoothing", "extends"}:
        raise InputError(f"{path}: expected the sections 'observation', 'tracker', 'background_refinement', "
                         "'body_refit' and 'smoothing' (and 'extends') only")
    if "extends" in doc:
        if str(path) in _seen:
            raise InputError(f"{path}: 'extends' loops back to itself")
        base = load_config(str(doc.pop("extends")), _seen + (str(path),))
        base.pop("source", None)
        doc = _merge(base, doc)
    doc.setdefault("observation", {})
    doc.setdefault("tracker", {})
    doc.setdefault("background_refinement", {})
    doc.setdefault("body_refit", {})
    doc.setdefault("smoothing", {})
    doc["source"] = str(path)
    return doc


def observer_from_config(rig: Any, background: Any, ocfg: dict[str, Any], model: str, voxel_m: float) -> Any:
    """The :class:`~torchtrack.tracking.observation.Observer` of a config's ``observation`` section."""
    from torchtrack.checks import InputError
    from torchtrack.occupancy import HullConfig
    from torchtrack.tracking.observation import Observer

    known = {"model", "voxel_m", "scale", "threshold", "min_views", "hull", "fill_static_subject", "workers"}
    unknown = set(ocfg) - known
    if unknown:
        raise InputError(f"observation config: unknown settings {sorted(unknown)}; known: {sorted(known)}")
    try:
        hull = HullConfig(**(ocfg.get("hull") or {}))
    except TypeError as exc:
        raise InputError(f"observation config, hull: {exc}") from None
    return Observer(rig, background, model, voxel_m, threshold=float(ocfg.get("threshold", 0.5)),
                    min_views=ocfg.get("min_views"), hull=hull)


def run(args: argparse.Namespace) -> int:
    import torch

    from torchtrack.io.outputs import TRACK_DIR, check_output

    t0 = time.perf_counter()
    replaces = check_output(args.out, TRACK_DIR, args.overwrite)  # before any work
    try:
        with torch.no_grad():
            return _run(args, t0)
    except (KeyboardInterrupt, NothingTracked) as exc:
        kept = (f"{args.out} is as it was before this run" if replaces else
                f"the TensorBoard logs of the frames tracked are in {args.out / 'tb'}"
                if (args.out / "tb").is_dir() else "nothing was written")
        if isinstance(exc, KeyboardInterrupt):
            print(f"torchtrack track: interrupted: no poses.npz written; {kept}", file=sys.stderr)
            return 130
        print(f"torchtrack track: error: {exc}; no poses.npz written; {kept}", file=sys.stderr)
        return EXIT_NOTHING_TRACKED


def _initial_pose(path: Path) -> tuple[Any, float | None, Any]:
    """The first valid frame's state of the poses.npz ``path``, its subject height (``subject_height_m``) and
    its subject's body (``body_urdf``: :func:`~torchtrack.tracking.refine.track_body`), each None where the file
    has none."""
    import numpy as np

    from torchtrack.checks import InputError
    from torchtrack.io.poses import load_poses
    from torchtrack.tracking.refine import track_body

    poses = load_poses(path)
    body = track_body(poses, str(path))  # checks the DOFs of both
    ok = np.flatnonzero(poses.valid)
    if ok.size == 0:
        raise InputError(f"{path}: no valid frame to start from")
    height = poses.extra.get("subject_height_m")
    return poses.angles[ok[0]], (float(height) if height is not None else None), body


def _run(args: argparse.Namespace, t0: float) -> int:
    import torch

    from torchtrack.background import BackgroundConfig, BackgroundModel
    from torchtrack.checks import InputError
    from torchtrack.io.outputs import TRACK_DIR, replacing
    from torchtrack.io.poses import save_poses
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.logging import RunLogger
    from torchtrack.skeleton import Skeleton
    from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
    from torchtrack.tracking.body_refit import BodyRefitConfig, track_with_body_refit
    from torchtrack.tracking.refine import RefineConfig, track_with_background_refinement
    from torchtrack.tracking.smoothing import SmoothingConfig, smooth_track

    cfg = load_config(args.config)
    ocfg = dict(cfg["observation"])
    model = args.model or ocfg.get("model", "bayes")
    voxel = float(args.voxel if args.voxel is not None else ocfg.get("voxel_m", 0.03))
    scale = float(args.scale if args.scale is not None else ocfg.get("scale", 1.0))
    if not 0.05 <= scale <= 1.0:
        raise InputError(f"--scale must be in [0.05, 1], got {scale:g}")
    if not 0.005 <= voxel <= 0.2:
        raise InputError(f"--voxel must be in [0.005, 0.2] m, got {voxel:g}")
    tcfg = TrackerConfig.from_dict(cfg["tracker"], cfg["source"])
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available to PyTorch")
    workers = args.workers if args.workers is not None else ocfg.get("workers", 0)
    if workers not in (0, 1):
        raise InputError(f"{cfg['source']}: observation.workers must be 0 or 1, got {workers!r}")

    rcfg = RefineConfig.from_dict(cfg["background_refinement"], cfg["source"])
    if args.refine_passes is not None:
        rcfg = replace(rcfg, passes=args.refine_passes)
    bcfg = BodyRefitConfig.from_dict(cfg["body_refit"], cfg["source"])
    if args.refit_passes is not None:
        bcfg = replace(bcfg, passes=args.refit_passes)
    scfg = SmoothingConfig.from_dict(cfg["smoothing"], cfg["source"])
    if args.smooth_hz is not None:
        scfg = replace(scfg, cutoff_hz=args.smooth_hz)

    folder = SequenceFolder(args.seq)
    W, H = (int(round(float(v) * scale)) for v in folder.rig.image_size_wh[0])
    rig = folder.rig.resized(W, H).float().to(device)
    fill = bool(args.fill_static_subject or ocfg.get("fill_static_subject", False))
    bg_config = BackgroundConfig(fill_static_subject=fill)
    if args.background_from_track is not None:
        from torchtrack.io.poses import load_poses
        from torchtrack.tracking.refine import background_from_track

        bg = background_from_track(folder, load_poses(args.background_from_track), bg_config, rcfg, (W, H), device,
                                   source=str(args.background_from_track), blob_specs=tcfg.blobs)
    else:
        bg = BackgroundModel.from_folder(folder, bg_config, size_wh=(W, H), device=device, progress=True)
    tracker = MarkerlessTracker(Skeleton.from_urdf().to(device), tcfg)
    if args.init_pose is not None:
        angles, height, body = _initial_pose(args.init_pose)
        angles = torch.as_tensor(angles, dtype=torch.float32, device=device)
        if body is not None and args.height is None:  # the file's own subject (e.g. an earlier run's fitted body)
            tracker.initialize_from_pose(angles, skeleton=body.to(device))
            if args.refit_passes is None:  # refitted only when asked (body_refit.given_body, --refit-passes)
                bcfg = bcfg.for_start(body_given=True)
        else:
            height = args.height or height or folder.meta.subject_height_m or 1.75
            tracker.initialize_from_pose(angles, height)
    if not bg.from_moving_sequence and rcfg.passes:
        log.info("%s: the background is measured from its background/ frames, not refined from the track",
                 args.seq)
        rcfg = replace(rcfg, passes=0)

    def make_observer(background: BackgroundModel) -> Any:
        return observer_from_config(rig, background, ocfg, model, voxel).to(device)

    with replacing(args.out, TRACK_DIR), RunLogger(args.out / "tb") as tb:
        passes: list[int] = []  # the passes run (the refinement may stop early)
        poses, _, bg = track_with_background_refinement(
            folder, bg, make_observer, tracker, rcfg, bg_config, args.start, args.stop, args.batch, device,
            logger=tb, log_every=args.log_every, workers=workers, on_pass=lambda p, _: passes.append(p))
        refits: list[bool] = []  # whether each body refit pass was kept
        kept_pass = poses.extra.get("refinement_pass")  # a kept body refit's track is a new record: carry it over
        poses, _ = track_with_body_refit(
            folder, lambda: make_observer(bg), tracker, poses, bcfg, args.start, args.stop, args.batch, device,
            log_dir=args.out / "tb", log_every=args.log_every, workers=workers,
            on_pass=lambda p, _, kept: refits.append(kept))
        if kept_pass is not None:
            poses.extra["refinement_pass"] = kept_pass
        if not poses.valid.any():  # raised inside: an earlier output is put back, not replaced by nothing
            raise NothingTracked(
                f"none of the {poses.num_frames} frames of {args.seq} was tracked: " + (
                    "the body was never found in the volume (nobody there, or the start was refused: see the "
                    "warnings above; --init-pose gives a start pose)" if tracker.subject is None else
                    "every frame was refused by the fit checks (see the warnings above)"))
        if tracker.subject is not None:
            poses = smooth_track(poses, tracker.subject.skeleton, scfg)
        save_poses(poses, args.out / "poses.npz")
    print(_summary(args.out, poses, len(passes), refits, time.perf_counter() - t0))
    return 0


class NothingTracked(Exception):
    """A track without a single valid frame: no poses.npz is written, and the command exits with
    :data:`EXIT_NOTHING_TRACKED`."""


#: Exit status of a run that tracked no frame (1 is Python's for an uncaught error; 2 bad input; 130 Ctrl-C).
EXIT_NOTHING_TRACKED = 3


def _summary(out: Path, poses: Any, passes: int, refits: list[bool], wall_s: float) -> str:
    """The closing line: frames tracked, the passes and the wall-clock rate of the whole command."""
    T, valid, reinit = poses.num_frames, poses.valid, poses.extra["reinitialised"]
    parts = [f"{T} frames, {int(valid.sum())} tracked ({int((~valid).sum())} invalid, {int(reinit.sum())} "
             f"(re)initialisations)"]
    if passes > 1:  # the refinement's tracks (the kept one tracked again for its logs counts too)
        kept = poses.extra.get("refinement_pass")
        parts.append(f"{passes} tracks of the background refinement" + (
            f", track {int(kept)} kept" if kept is not None else ""))
    if refits:
        parts.append(f"{len(refits)} body refit{'s' * (len(refits) > 1)}, {sum(refits)} kept")
    smoothed = float(poses.extra.get("smoothing_cutoff_hz", 0.0))
    if smoothed:
        parts.append(f"smoothed at {smoothed:g} Hz")
    return (f"wrote {out / 'poses.npz'}: {'; '.join(parts)}; {wall_s:.0f} s wall clock, {T / wall_s:.2f} frames/s; "
            f"TensorBoard logs in {out / 'tb'}")
