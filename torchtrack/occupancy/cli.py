"""`torchtrack observe`: 3D occupancy of a sequence (Bayesian grid, hull or silhouette carving) with
TensorBoard logs and a sparse ``occupancy.npz``."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from torchtrack.checks import InputError

log = logging.getLogger(__name__)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("observe", help="3D occupancy of a sequence folder, logged to TensorBoard",
                       description="Compute per-frame occupancy of a sequence folder and write OUT/occupancy.npz "
                                   "(occupied voxel centres and sizes per frame) and TensorBoard logs in OUT/tb.")
    p.add_argument("seq", type=Path, metavar="SEQ", help="sequence folder (calibration.toml, video/ or frames/)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="output folder: new, empty, or an earlier run's (with --overwrite)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier run's occupancy.npz and TensorBoard logs in DIR (default: refuse)")
    p.add_argument("--model", choices=("bayes", "hull", "silhouette"), default="bayes",
                   help="Bayesian occupancy grid, hierarchical colour hull or silhouette carving "
                        "(default: %(default)s)")
    p.add_argument("--voxel", type=float, default=0.02, metavar="M",
                   help="voxel size in metres, the hull's finest level (default: %(default)s)")
    p.add_argument("--scale", type=float, default=1.0, metavar="F",
                   help="process the images at this fraction of their size (default: %(default)s)")
    p.add_argument("--window", type=int, default=1, metavar="K",
                   help="Bayesian grid: sample a K x K pixel window around each voxel's projection, K odd "
                        "(default: %(default)s)")
    p.add_argument("--min-views", type=int, default=None, metavar="N",
                   help="cameras that must see a voxel; the volume is the floor that many see, up to 2.1 m "
                        "(default: Bayesian grid half of them, at least three; hull all)")
    p.add_argument("--start", type=int, default=0, metavar="FRAME",
                   help="first frame to process, a 0-based frame index (default: %(default)s)")
    p.add_argument("--stop", type=int, default=None, metavar="FRAME",
                   help="frame index to stop before, exclusive (default: the end of the sequence)")
    p.add_argument("--batch", type=int, default=4, metavar="N",
                   help="frames per batch, Bayesian grid and silhouettes (default: %(default)s)")
    p.add_argument("--log-every", type=int, default=10, metavar="N",
                   help="log the point cloud and images every N frames (0: never) (default: %(default)s)")
    p.add_argument("--device", default="cpu", help="torch device: cpu or cuda (default: %(default)s)")
    p.add_argument("--fill-static-subject", action="store_true",
                   help="without background/ frames: paint the parts of the subject that never move out of the "
                        "estimated background, for a subject balancing in place (default: off)")
    p.add_argument("--background-from-track", type=Path, default=None, metavar="POSES",
                   help="without background/ frames: estimate the background from the frames each pixel is "
                        "clearest of the body tracked in POSES, the poses.npz of a `torchtrack track` run on SEQ "
                        "(default: from background/, else estimated from the video)")
    p.add_argument("--near-fraction", type=float, default=0.0, metavar="F",
                   help="with --background-from-track: a pixel without enough frames (RefineConfig.clear_frames) "
                        "at least F of the image's larger side clear of the tracked body keeps the plain estimate, "
                        "which brings back e.g. a stance foot's toes (0: off) (default: %(default)s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from torchtrack.io.outputs import OBSERVE_DIR, check_output

    replaces = check_output(args.out, OBSERVE_DIR, args.overwrite)  # before any work
    try:
        with torch.no_grad():
            return _run(args)
    except KeyboardInterrupt:
        kept = (f"{args.out} is as it was before this run" if replaces else
                f"the TensorBoard logs of the frames observed are in {args.out / 'tb'}"
                if (args.out / "tb").is_dir() else "nothing was written")
        print(f"torchtrack observe: interrupted: no occupancy.npz written; {kept}", file=sys.stderr)
        return 130


def _run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch
    from tqdm import tqdm

    from torchtrack.background import BackgroundConfig, BackgroundModel
    from torchtrack.io.atomic import atomic_path
    from torchtrack.io.outputs import OBSERVE_DIR, replacing
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.logging import RunLogger
    from torchtrack.occupancy import (BayesConfig, BayesianGrid, HierarchicalHull, HullConfig, SilhouetteCarving,
                                      capture_views, grid_from_rig)

    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available to PyTorch")
    if not 0.05 <= args.scale <= 1.0:
        raise InputError(f"--scale must be in [0.05, 1], got {args.scale:g}")
    folder = SequenceFolder(args.seq)
    full = folder.rig
    W, H = (int(round(float(v) * args.scale)) for v in full.image_size_wh[0])
    rig = full.resized(W, H).float().to(device)
    bg_config = BackgroundConfig(fill_static_subject=args.fill_static_subject)
    if not 0.0 <= args.near_fraction < 1.0:  # NaN too
        raise InputError(f"--near-fraction must be in [0, 1) (0: off), got {args.near_fraction}")
    if args.near_fraction and args.background_from_track is None:
        raise InputError("--near-fraction changes the background from a track: give --background-from-track")
    if args.background_from_track is not None:
        from torchtrack.io.poses import load_poses
        from torchtrack.tracking.refine import RefineConfig, background_from_track

        refine = RefineConfig(near_fraction=args.near_fraction)
        bg = background_from_track(folder, load_poses(args.background_from_track), bg_config, refine, (W, H),
                                   device=device, source=str(args.background_from_track))
    else:
        bg = BackgroundModel.from_folder(folder, bg_config, size_wh=(W, H), device=device, progress=True)
    if args.min_views is None:
        args.min_views = capture_views(rig.num_cameras, args.model)
    elif not 1 <= args.min_views <= rig.num_cameras:
        raise InputError(f"--min-views {args.min_views}: the rig has {rig.num_cameras} cameras")
    spec = grid_from_rig(rig, args.voxel, min_views=args.min_views)
    if args.model == "bayes":
        model = BayesianGrid(rig, spec, bg, BayesConfig(window=args.window, min_views=args.min_views)).to(device)
    elif args.model == "silhouette":
        model = SilhouetteCarving(rig, spec, bg, min_views=args.min_views).to(device)
    else:
        model = HierarchicalHull(rig, HullConfig(lower_m=spec.lower_m, upper_m=spec.upper_m,
                                                 finest_voxel_m=args.voxel, min_views=args.min_views))
    centres_all = spec.centres(device=device)
    stop = folder.num_frames if args.stop is None else min(args.stop, folder.num_frames)
    frames_out, centres_out, sizes_out = [], [], []
    with (replacing(args.out, OBSERVE_DIR), RunLogger(args.out / "tb") as tb,
          tqdm(total=stop - args.start, unit="frame", desc="observe") as bar):
        for batch in folder.iter_batches(args.batch, args.start, stop, device=device, size_wh=(W, H)):
            t0 = time.perf_counter()
            if args.model == "hull":
                results = [model.from_images(bg, img) for img in batch.images]
                per_frame = [(v.centres, v.sizes) for v in results]
            else:
                occ = model(batch.images).occupied()  # (B, V)
                per_frame = [(centres_all[o], torch.full((int(o.sum()),), spec.voxel_size_m, device=device))
                             for o in occ]
            ms = 1e3 * (time.perf_counter() - t0) / len(per_frame)
            for i, (c, s) in enumerate(per_frame):
                t = int(batch.frame_index[i])
                frames_out.append(t)
                centres_out.append(c.cpu().float().numpy())
                sizes_out.append(s.cpu().float().numpy())
                tb.scalars(t, voxels=float(c.shape[0]), volume_m3=float((s ** 3).sum()), ms_per_frame=ms,
                           cameras_unreadable=float((~batch.valid[i]).sum()))
                if args.log_every > 0 and (t - args.start) % args.log_every == 0:
                    tb.occupancy_cloud(t, "occupancy/voxels", c)
                    fg = torch.sigmoid(bg.log_uniform - bg.log_likelihood(batch.images[i:i + 1]))[0]  # (C, H, W)
                    tb.probability_images(t, "foreground/probability", torch.nan_to_num(fg, nan=0.0), rig.names)
                    tb.camera_images(t, "cameras/input", torch.nan_to_num(batch.images[i], nan=0.0), rig.names)
            bar.update(len(per_frame))
        offsets = np.cumsum([0] + [len(c) for c in centres_out])
        with atomic_path(args.out / "occupancy.npz", suffix=".npz") as tmp:
            np.savez_compressed(tmp, frame_index=np.asarray(frames_out, np.int64), frame_offsets=offsets,
                                centres=np.concatenate(centres_out) if centres_out else np.zeros((0, 3), np.float32),
                                sizes=np.concatenate(sizes_out) if sizes_out else np.zeros((0,), np.float32),
                                grid_lower_m=np.asarray(spec.lower_m), grid_upper_m=np.asarray(spec.upper_m),
                                voxel_size_m=np.float64(spec.voxel_size_m), model=np.asarray(args.model))
    print(f"wrote {args.out / 'occupancy.npz'} ({len(frames_out)} frames, mean "
          f"{offsets[-1] / max(1, len(frames_out)):.0f} voxels) and TensorBoard logs in {args.out / 'tb'}")
    return 0
