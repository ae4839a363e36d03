"""`torchtrack track`: markerless tracking of a sequence folder into ``poses.npz`` with TensorBoard logs."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

#: The built-in tracking config (torchtrack.tracking.pipeline.DEFAULT_CONFIG; not imported here: it imports torch).
DEFAULT_CONFIG = "markerless.yaml"

#: Exit status of a run that tracked no frame (1 is Python's for an uncaught error; 2 bad input; 130 Ctrl-C).
EXIT_NOTHING_TRACKED = 3


def _shipped_config() -> dict[str, Any] | None:
    """The built-in ``configs/markerless.yaml`` (not one of that name in the working directory), for the
    defaults the help quotes; None where it cannot be read (the help then names the settings only)."""
    from torchtrack.resources import builtin_config
    from torchtrack.tracking.pipeline import load_config

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
        "track", help="3D body tracking of a sequence folder, from video or markers",
        description="Track the body through a sequence folder from its occupancy (Bayesian grid or colour hull), "
                    "with blobs fitted by EM, joint goals and CCD inverse kinematics. Writes OUT/poses.npz "
                    "(docs/formats.md) and TensorBoard logs in OUT/tb. The tracker starts at the first frame that "
                    "shows one whole person, in any pose (or give --init-pose). Options marked 'default from --config' "
                    "override that setting of the tracking config.")
    p.add_argument("seq", type=Path, nargs="+", metavar="SEQ",
                   help="sequence folder (calibration.toml, video/ or frames/, background/; or markers2d.npz); "
                        "several are tracked together in lockstep, --batch-size at a time, each into DIR/<its "
                        "folder's name>")
    p.add_argument("--mode", choices=("auto", "markerless", "markers"), default="auto",
                   help="markerless: from the videos; markers: from markers2d.npz, marker detections, by the "
                        "annealed particle filter; auto: markers where SEQ has markers2d.npz and no video/ or "
                        "frames/ (default: %(default)s)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="output folder: new, empty, or an earlier track's (with --overwrite); with several SEQ, "
                        "the folder of their output folders")
    p.add_argument("--batch-size", type=int, default=16, metavar="B",
                   help="with several SEQ: how many are tracked at a time in lockstep, one batched per-frame step for "
                        "all; each is tracked as alone (default: %(default)s)")
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
                        "init-pose`'s), with its body where the file has one (default: the body searched for in the "
                        "first frame that shows one person)")
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
    p.add_argument("--threads", type=int, default=1, metavar="N",
                   help="intra-op threads of the tracking process; the tracker's small operations gain nothing "
                        "from more, and more run many times slower beside a busy process; an observation worker "
                        "gets the other cores (default: %(default)s)")
    p.add_argument("--workers", type=int, choices=(0, 1), default=None,
                   help=f"1: read and observe frames in a worker process ahead of the tracker (CPU); 0: in this "
                        f"process ({conf('observation.workers')})")
    p.add_argument("--fill-static-subject", action=argparse.BooleanOptionalAction, default=None,
                   help=f"without background/ frames: paint the parts of the subject that never move out of the "
                        f"background estimated from the video (a subject balancing or turning in place); --no-... "
                        f"keeps them ({conf('observation.fill_static_subject')})")
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


def run(args: argparse.Namespace) -> int:
    from torchtrack.io.outputs import TRACK_DIR, check_output, replacing
    from torchtrack.io.poses import save_poses
    from torchtrack.tracking.pipeline import NothingTracked, track

    from torchtrack.checks import InputError
    from torchtrack.markers.track import is_marker_folder

    if args.batch_size < 1:
        raise InputError(f"--batch-size must be >= 1, got {args.batch_size}")
    markers = [args.mode == "markers" or (args.mode == "auto" and is_marker_folder(s)) for s in args.seq]
    if any(markers):
        if not all(markers):
            video = [str(s) for s, m in zip(args.seq, markers) if not m]
            raise InputError(f"marker folders (markers2d.npz, no video) and video folders ({', '.join(video)}) are "
                             "tracked by different methods: track them in separate runs")
        return _run_markers(args)
    if len(args.seq) > 1:
        return _run_many(args)
    args.seq = args.seq[0]
    replaces = check_output(args.out, TRACK_DIR, args.overwrite)  # before any work
    try:
        with replacing(args.out, TRACK_DIR):  # an error or Ctrl-C inside puts an earlier output back
            result = track(
                args.seq, config=args.config, model=args.model, voxel_m=args.voxel, scale=args.scale,
                init_pose=args.init_pose, height_m=args.height, start=args.start, stop=args.stop, batch=args.batch,
                device=args.device, workers=args.workers, fill_static_subject=args.fill_static_subject,
                refine_passes=args.refine_passes, refit_passes=args.refit_passes, smooth_hz=args.smooth_hz,
                background_from_track=args.background_from_track, threads=args.threads, log_dir=args.out / "tb",
                log_every=args.log_every)
            save_poses(result.poses, args.out / "poses.npz")
    except (KeyboardInterrupt, NothingTracked) as exc:
        kept = (f"{args.out} is as it was before this run" if replaces else
                f"the TensorBoard logs of the frames tracked are in {args.out / 'tb'}"
                if (args.out / "tb").is_dir() else "nothing was written")
        if isinstance(exc, KeyboardInterrupt):
            print(f"torchtrack track: interrupted: no poses.npz written; {kept}", file=sys.stderr)
            return 130
        print(f"torchtrack track: error: {exc}; no poses.npz written; {kept}", file=sys.stderr)
        return EXIT_NOTHING_TRACKED
    print(_summary(args.out, result))
    return 0


def _run_markers(args: argparse.Namespace) -> int:
    """``--mode markers``: the annealed particle filter on each SEQ's marker detections into OUT/poses.npz (several:
    ``--batch-size`` at a time in lockstep, each into ``OUT/<name>``; one that cannot be read is reported with its
    name and leaves its folder as it was, the others are written)."""
    from torchtrack.checks import InputError
    from torchtrack.io.outputs import TRACK_DIR, check_output, replacing
    from torchtrack.logging import RunLogger
    from torchtrack.markers.track import load_marker_sequence, track_marker_sequences
    from torchtrack.tracking.pipeline import intra_op_threads

    one = len(args.seq) == 1
    outs = [args.out] if one else _many_outputs(args)
    if one:
        check_output(args.out, TRACK_DIR, args.overwrite)  # before any work
    failed, written = 0, []
    with intra_op_threads(args.threads):
        for first in range(0, len(args.seq), args.batch_size):
            batch = []  # (folder, its output, the loaded sequence)
            for seq, out in zip(args.seq[first:first + args.batch_size], outs[first:first + args.batch_size]):
                try:
                    batch.append((seq, out, load_marker_sequence(seq, args.start, args.stop)))
                except InputError as exc:
                    if one:
                        raise
                    failed += 1
                    print(f"torchtrack track: {seq}: failed: {exc}; no poses.npz written", file=sys.stderr)
            outputs = []  # each output's replacement (an error puts its earlier output back) and logger
            try:
                for _, out, _ in batch:
                    cm = replacing(out, TRACK_DIR)
                    cm.__enter__()  # the earlier output moved aside before the logger writes
                    outputs.append([cm, None])
                    outputs[-1][1] = RunLogger(out / "tb").__enter__()
                results = track_marker_sequences([b[2] for b in batch], loggers=[o[1] for o in outputs],
                                                 log_every=args.log_every) if batch else []
            except BaseException as exc:  # Ctrl-C, or an error of the batch as a whole: its folders as they were
                for cm, logger in outputs:
                    if logger is not None:
                        logger.__exit__(None, None, None)
                    cm.__exit__(type(exc), exc, exc.__traceback__)
                if isinstance(exc, KeyboardInterrupt):
                    print("torchtrack track: interrupted: this batch's poses.npz not written"
                          + (f"; written before it: {', '.join(map(str, written))}" if written else ""),
                          file=sys.stderr)
                    return 130
                if one or not isinstance(exc, Exception):
                    raise
                failed += len(batch)
                for seq, _, _ in batch:
                    print(f"torchtrack track: {seq}: failed with its batch: {exc}; no poses.npz written",
                          file=sys.stderr)
                continue
            for (seq, out, _), (cm, logger), result in zip(batch, outputs, results):
                logger.__exit__(None, None, None)
                if one and isinstance(result, Exception):
                    cm.__exit__(type(result), result, result.__traceback__)
                    raise result
                if _write_result(seq, out, cm, result, _marker_summary):
                    written.append(out / "poses.npz")
                else:
                    failed += 1
    if failed:
        print(f"torchtrack track: {failed} of {len(args.seq)} sequences failed (above); the others were written",
              file=sys.stderr)
        return 1
    return 0


def _many_outputs(args: argparse.Namespace) -> list[Path]:
    """Several sequences' output folders ``OUT/<name>``, checked before any work: ``--batch-size``, names that
    collide, an ``--out`` that is a file, an existing output without ``--overwrite``, options of one sequence."""
    from torchtrack.checks import InputError
    from torchtrack.io.outputs import TRACK_DIR, check_output

    if args.batch_size < 1:
        raise InputError(f"--batch-size must be >= 1, got {args.batch_size}")
    names = [Path(s).resolve().name for s in args.seq]
    seen: dict[str, Path] = {}
    for name, seq in zip(names, args.seq):
        if name in seen:
            raise InputError(f"two sequences are named {name!r} ({seen[name]} and {seq}); their outputs would both "
                             f"go to {args.out / name}: track them into different --out folders")
        seen[name] = seq
    if args.out.exists() and not args.out.is_dir():
        raise InputError(f"--out {args.out}: is a file; with several sequences it is the folder of their outputs")
    outs = [args.out / name for name in names]
    for out in outs:
        check_output(out, TRACK_DIR, args.overwrite)
    for s in ("init_pose", "background_from_track"):
        if getattr(args, s) is not None:
            raise InputError(f"--{s.replace('_', '-')} names one sequence's file: track that sequence alone")
    return outs


def _run_many(args: argparse.Namespace) -> int:
    """Several sequences, ``--batch-size`` at a time in lockstep, each into ``OUT/<name>`` (checked before any work);
    one that fails is reported with its name and leaves its folder as it was, the others are written."""
    from torchtrack.io.outputs import TRACK_DIR, replacing
    from torchtrack.tracking.pipeline import track_many

    outs = _many_outputs(args)
    outputs = [replacing(out, TRACK_DIR) for out in outs]  # an error puts a sequence's earlier output back
    for cm in outputs:
        cm.__enter__()
    results = []
    try:
        results = track_many(
            list(args.seq), batch_size=args.batch_size, log_dirs=[out / "tb" for out in outs], threads=args.threads,
            config=args.config, model=args.model, voxel_m=args.voxel, scale=args.scale, height_m=args.height,
            start=args.start, stop=args.stop, batch=args.batch, device=args.device,
            fill_static_subject=args.fill_static_subject, refine_passes=args.refine_passes,
            refit_passes=args.refit_passes, smooth_hz=args.smooth_hz, log_every=args.log_every)
    except BaseException as exc:  # Ctrl-C, or an error of the batch as a whole: every folder as it was
        for cm in outputs:
            cm.__exit__(type(exc), exc, exc.__traceback__)
        if isinstance(exc, KeyboardInterrupt):
            print("torchtrack track: interrupted: no poses.npz written", file=sys.stderr)
            return 130
        raise
    failed = sum(not _write_result(seq, out, cm, result, _summary)
                 for seq, out, cm, result in zip(args.seq, outs, outputs, results))
    if failed:
        print(f"torchtrack track: {failed} of {len(results)} sequences failed (above); the others were written",
              file=sys.stderr)
        return 1
    return 0


def _write_result(seq: Path, out: Path, replacement: Any, result: Any, summary: Callable[[Path, Any], str]) -> bool:
    """One sequence's result of a batch: its poses.npz written and ``summary`` printed (True), or the exception it
    failed with reported by name and its earlier output put back (False); ``replacement`` is the entered
    :func:`~torchtrack.io.outputs.replacing` of ``out``, closed here."""
    from torchtrack.io.poses import save_poses

    if isinstance(result, Exception):
        replacement.__exit__(type(result), result, result.__traceback__)
        print(f"torchtrack track: {seq}: failed: {result}; no poses.npz written", file=sys.stderr)
        return False
    try:
        save_poses(result.poses, out / "poses.npz")
    except BaseException as exc:
        replacement.__exit__(type(exc), exc, exc.__traceback__)
        raise
    replacement.__exit__(None, None, None)
    print(summary(out, result))
    return True


def _marker_summary(out: Path, result: Any) -> str:
    """A marker track's closing line: frames, markers, frames tracked and the wall-clock rate."""
    T, M = result.poses.num_frames, len(result.poses.marker_names)
    return (f"wrote {out / 'poses.npz'}: {T} frames of {M} markers by the annealed particle filter, "
            f"{int(result.poses.valid.sum())} tracked; {result.seconds:.0f} s wall clock, {T / result.seconds:.2f} "
            "frames/s")


def _summary(out: Path, result: Any) -> str:
    """The closing line: frames tracked, the passes and the wall-clock rate of the whole track."""
    poses, passes, refits, wall_s = result.poses, result.refinement_tracks, result.refits, result.seconds
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
