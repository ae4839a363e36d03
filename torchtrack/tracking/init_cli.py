"""``torchtrack init-pose``: the start pose and body for ``torchtrack track --init-pose``, from 3D keypoints.

    torchtrack init-pose KEYPOINTS.trc --out START.npz [--frame N] [--up y|z] [--scale-only]

The tracker finds the first frame's pose by itself; a recording it starts wrongly on (a pose the few cameras
leave ambiguous) can be given it. Another system's 3D keypoints of that frame (Pose2Sim's triangulation, joint centres from markers) give it: the pose and the
subject's bone lengths are fitted to them (:func:`~torchtrack.tracking.landmark_fit.fit_to_landmarks`) and
written as a one-frame ``poses.npz`` that carries the fitted body.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "init-pose", help="fit a start pose and body to 3D keypoints (for --init-pose)",
        description="Fit the skeleton's pose and bone lengths to the 3D keypoints of one frame of a TRC file and "
                    "write them as a one-frame poses.npz for `torchtrack track --init-pose`. Keypoint names: "
                    "BODY_25B as Pose2Sim writes them (RHip, LKnee, Neck, Head, ...) or torchtrack's joint "
                    "names (pelvis, l_knee, ...); the hips and at least one shoulder are needed.")
    p.add_argument("keypoints", type=Path, metavar="TRC", help="TRC file of 3D keypoints (metres, mm or cm)")
    p.add_argument("--out", type=Path, required=True, metavar="FILE",
                   help="poses.npz to write: the fitted pose as one frame, with the fitted body; a new file, or an "
                        "earlier poses file (with --overwrite) (required)")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier poses file at FILE (default: refuse)")
    p.add_argument("--frame", type=int, default=0, metavar="N",
                   help="row of the TRC to fit, 0-based: the sequence's first tracked frame (default: 0)")
    p.add_argument("--up", choices=("y", "z"), default="y",
                   help="the TRC's vertical axis: y for OpenSim / Pose2Sim files, z for a Z-up world "
                        "(default: y)")
    p.add_argument("--scale-only", action="store_true",
                   help="scale the template body to the keypoints' height instead of fitting each bone's length "
                        "(default: off, the lengths are fitted)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from torchtrack.checks import InputError
    from torchtrack.io.outputs import POSES_FILE, check_output
    from torchtrack.io.pose2sim import landmarks_from_keypoints
    from torchtrack.io.poses import save_poses
    from torchtrack.io.trc import read_trc, y_up_to_world
    from torchtrack.skeleton import Skeleton
    from torchtrack.tracking.landmark_fit import fit_to_landmarks, initial_pose

    check_output(args.out, POSES_FILE, args.overwrite)  # before any work
    trc = read_trc(args.keypoints)
    xyz = trc.positions_m()
    if not 0 <= args.frame < xyz.shape[0]:
        raise InputError(f"{args.keypoints}: --frame {args.frame} is out of range (the file has {xyz.shape[0]} rows)")
    xyz = y_up_to_world(xyz[args.frame]) if args.up == "y" else xyz[args.frame]
    generic = Skeleton.from_urdf()
    names, points = landmarks_from_keypoints(trc.marker_names, xyz, tuple(generic.output_names))
    finite = np.isfinite(points).all(-1)
    names, points = [n for n, ok in zip(names, finite) if ok], points[finite]
    # The root's rotation needs trunk points off the hips' line (a pelvis made of the hips' mean is on it).
    if not ({"l_hip", "r_hip"} <= set(names) and {"l_shoulder", "r_shoulder"} & set(names)):
        raise InputError(f"{args.keypoints}: frame {args.frame} lacks the hips or a shoulder, which place the body; "
                         f"usable keypoints: {names or 'none'} (expected Pose2Sim's BODY_25B names: RHip, LHip, "
                         "RShoulder, ..., or torchtrack's: r_hip, l_hip, r_shoulder, ...)")
    try:
        with torch.no_grad():
            angles, body = fit_to_landmarks(generic, names, points, fit_bones=not args.scale_only)
    except InputError as exc:
        raise InputError(f"{args.keypoints}, frame {args.frame}: {exc}") from None
    with torch.no_grad():
        fitted = body.forward(angles[None]).output_points[0].cpu().numpy()
    idx = [list(body.output_names).index(n) for n in names]
    error_mm = 1e3 * np.linalg.norm(fitted[idx] - points, axis=-1)
    save_poses(initial_pose(body, angles, fps=trc.rate_hz), args.out)
    print(f"wrote {args.out}: {len(names)} keypoints fitted ({', '.join(names)}), a {body.height():.2f} m body, "
          f"{error_mm.mean():.1f} mm from the keypoints on average (worst {names[int(error_mm.argmax())]}, "
          f"{error_mm.max():.1f} mm)")
    if error_mm.mean() > 30.0:  # a fit this far off is a wrong --up axis, wrong names or units
        print(f"warning: the fit is far from the keypoints; check --up ({args.up}), the names and the units")
    up = {n: p[2] for n, p in zip(names, points)}
    shoulders = np.mean([up[n] for n in ("l_shoulder", "r_shoulder") if n in up])
    if shoulders - 0.5 * (up["l_hip"] + up["r_hip"]) < 0.2:  # a start is upright: Z up in the world
        print(f"warning: the shoulders are not above the hips in the world (Z up); check --up ({args.up})")
    return 0
