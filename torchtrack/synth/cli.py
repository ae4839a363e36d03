"""`torchtrack synth`: render a synthetic multi-camera sequence folder."""

from __future__ import annotations

import argparse
import dataclasses


def add_parser(sub: argparse._SubParsersAction) -> None:
    from torchtrack.synth.motion import MOTIONS

    p = sub.add_parser("synth", help="render a synthetic multi-camera sequence (video, calibration, ground truth)",
                       description="Render a body of ellipsoids moving in a textured room, seen by a ring of "
                                   "cameras, into a sequence folder (calibration.toml, background/, video/, "
                                   "gt.npz, meta.toml).")
    p.add_argument("--out", required=True, help="sequence folder to write (replaced atomically)")
    p.add_argument("--motion", default="walk",
                   help=f"procedural motion ({', '.join(MOTIONS)}) or a .bvh file (default: walk)")
    p.add_argument("--duration", type=float, default=3.0, help="seconds of motion after the starfish start")
    p.add_argument("--starfish", type=float, default=1.0, help="seconds of starfish pose at the start")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--height", type=float, default=1.75, help="subject height in metres (procedural motions)")
    p.add_argument("--cameras", type=int, default=8, help="number of cameras on the ring")
    p.add_argument("--size", default="640x480", help="image size WxH")
    p.add_argument("--radius", type=float, default=3.5, help="camera ring radius in metres")
    p.add_argument("--background-frames", type=int, default=20)
    p.add_argument("--format", choices=("mp4", "png"), default="mp4", help="video files or PNG frames")
    p.add_argument("--noise", type=float, default=2.0, help="sensor noise std in 8-bit levels")
    p.add_argument("--illumination-change", type=float, default=0.0,
                   help="amplitude of a smooth global gain change over the sequence (0 = off, e.g. 0.25)")
    p.add_argument("--shadow", action="store_true", help="soft shadow of the body on the floor")
    p.add_argument("--distractor", action="store_true",
                   help="a static object absent from the background frames, seen by some views")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--reuse", action="store_true",
                   help="keep OUT as it is when it already holds this sequence: rendered with these settings and "
                        "today's configs/body.urdf and blobs.yaml (meta.toml's [synth] table); render it otherwise")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from torchtrack.checks import InputError
    from torchtrack.synth.scene import SceneConfig
    from torchtrack.synth.sequence import RigConfig, SynthConfig, is_current, write_sequence

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 640x480, got {args.size!r}") from None
    cfg = SynthConfig(
        motion=args.motion, duration_s=args.duration, starfish_s=args.starfish, fps=args.fps,
        subject_height_m=args.height, background_frames=args.background_frames, video_format=args.format,
        rig=RigConfig(num_cameras=args.cameras, width=w, height=h, radius_m=args.radius),
        scene=dataclasses.replace(SceneConfig(), noise_std=args.noise / 255.0,
                                  illumination_change=args.illumination_change, shadow=args.shadow,
                                  distractor=args.distractor, seed=args.seed),
        seed=args.seed)
    if args.reuse and is_current(args.out, cfg):
        print(f"{args.out} already holds this sequence (--reuse): kept")
        return 0
    out = write_sequence(cfg, args.out, device=args.device)
    print(f"wrote synthetic sequence to {out}")
    return 0
