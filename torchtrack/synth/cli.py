"""`torchtrack synth`: render a synthetic multi-camera sequence folder."""

from __future__ import annotations

import argparse
import dataclasses


def add_parser(sub: argparse._SubParsersAction) -> None:
    from torchtrack.synth.motion import MOTIONS

    p = sub.add_parser("synth", help="render a synthetic multi-camera sequence with ground truth",
                       description="Render a body of ellipsoids moving in a textured room, seen by a ring of "
                                   "cameras, into a sequence folder (calibration.toml, background/, video/, "
                                   "gt.npz, meta.toml). `synth markers`: project a C3D capture's real markers "
                                   "into a calibrated rig through a simulated detector instead (calibration.toml, "
                                   "markers2d.npz, gt.npz).")
    p.add_argument("kind", nargs="?", choices=("video", "markers"), default="video",
                   help="video: a rendered sequence; markers: 2D marker detections of a C3D capture (--motion "
                        "FILE.c3d) in a real rig (default: %(default)s)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="sequence folder to write, written whole or not at all: new, empty, or an earlier "
                        "synthetic sequence (with --overwrite or --reuse)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier synthetic sequence in DIR (a folder holding anything else is refused) "
                        "(default: refuse)")
    p.add_argument("--motion", default="walk", metavar="MOTION",
                   help=f"procedural motion ({', '.join(MOTIONS)}), a .bvh file or a .c3d marker capture "
                        "(default: %(default)s)")
    p.add_argument("--duration", type=float, default=3.0, metavar="SEC",
                   help="seconds of motion after the starfish start (default: %(default)s)")
    p.add_argument("--starfish", type=float, default=1.0, metavar="SEC",
                   help="seconds of starfish pose at the start (default: %(default)s)")
    p.add_argument("--fps", type=float, default=30.0, metavar="HZ",
                   help="frame rate in frames per second; a .bvh or .c3d file is resampled to it "
                        "(default: %(default)s)")
    p.add_argument("--height", type=float, default=1.75, metavar="M",
                   help="subject height in metres, procedural motions (a .bvh or .c3d: its own) "
                        "(default: %(default)s)")
    p.add_argument("--cameras", type=int, default=8, metavar="N",
                   help="number of cameras on the ring (default: %(default)s)")
    p.add_argument("--size", default="640x480", metavar="WxH",
                   help="image size in pixels, width x height (default: %(default)s)")
    p.add_argument("--radius", type=float, default=3.5, metavar="M",
                   help="camera ring radius in metres (default: %(default)s)")
    p.add_argument("--background-frames", type=int, default=20, metavar="N",
                   help="frames of the empty room written to background/ (default: %(default)s)")
    p.add_argument("--format", choices=("mp4", "png"), default="mp4",
                   help="mp4 video files or PNG frames (default: %(default)s)")
    p.add_argument("--noise", type=float, default=2.0, metavar="LEVELS",
                   help="sensor noise standard deviation in 8-bit grey levels (default: %(default)s)")
    p.add_argument("--illumination-change", type=float, default=0.0, metavar="A",
                   help="amplitude A of a global gain 1 + A sin(2 pi t / T) over the sequence, a fraction "
                        "(e.g. 0.25; 0: off) (default: %(default)s)")
    p.add_argument("--shadow", action="store_true", help="soft shadow of the body on the floor (default: off)")
    p.add_argument("--distractor", action="store_true",
                   help="a static box absent from the background frames, seen by some views (default: off)")
    p.add_argument("--markers", action="store_true",
                   help="coloured balls on the body (Plug-in-Gait places), for `torchtrack detect`; writes "
                        "marker_labels.csv (frame 0's labels) and the markers' truth in gt.npz (default: off)")
    p.add_argument("--marker-radius", type=float, default=0.02, metavar="M",
                   help="radius of the balls in metres, with --markers (default: %(default)s)")
    p.add_argument("--marker-colour", default="0.95,0.1,0.75", metavar="R,G,B",
                   help="RGB albedo of the balls in [0, 1], with --markers (default: %(default)s, magenta)")
    p.add_argument("--seed", type=int, default=0, metavar="N",
                   help="seed of the sensor noise and the room textures (default: %(default)s)")
    p.add_argument("--device", default="cpu", help="torch device to render on: cpu or cuda (default: %(default)s)")
    m = p.add_argument_group("markers (synth markers)")
    m.add_argument("--calibration", metavar="TOML",
                   help="the rig the markers are seen by (default: the Qualisys rig of ../shared/data/pose2sim_demo)")
    m.add_argument("--p-miss", type=float, default=0.2, metavar="P",
                   help="probability that a marker a camera sees is not detected (default: %(default)s)")
    m.add_argument("--false-rate", type=float, default=0.1, metavar="N",
                   help="false detections per view and frame, Poisson mean (default: %(default)s)")
    m.add_argument("--sigma", type=float, default=2.0, metavar="PX",
                   help="pixel noise of each detection, standard deviation per axis (default: %(default)s)")
    p.add_argument("--reuse", action="store_true",
                   help="keep DIR as it is when it already holds this sequence: rendered with these settings and "
                        "today's configs/body.urdf and blobs.yaml (meta.toml's [synth] table); render it otherwise, "
                        "replacing an earlier synthetic sequence there")
    p.set_defaults(func=run)


#: ``synth markers``' default rig: the real Qualisys rig of the Pose2Sim demo, as the repository's data holds it.
DEFAULT_MARKER_RIG = "../shared/data/pose2sim_demo/calibration/Calib_qualisys_pose2sim.toml"


def run_markers(args: argparse.Namespace) -> int:
    """``torchtrack synth markers``: the folder of :func:`~torchtrack.markers.capture.simulated_capture`."""
    from pathlib import Path

    from torchtrack.cameras import load_calibration
    from torchtrack.checks import InputError
    from torchtrack.io.outputs import MARKERS_DIR, check_output, replacing
    from torchtrack.markers.capture import simulated_capture, write_marker_capture
    from torchtrack.markers.simulate import DetectorModel

    if Path(args.motion).suffix.lower() != ".c3d":
        raise InputError(f"synth markers: --motion {args.motion}: give a .c3d marker capture")
    calib = Path(args.calibration or DEFAULT_MARKER_RIG)
    if not calib.is_file():
        raise InputError(f"synth markers: --calibration {calib}: no such file"
                         + ("" if args.calibration else " (the default rig; pass --calibration TOML)"))
    model = DetectorModel(p_miss=args.p_miss, false_rate=args.false_rate, sigma_px=args.sigma)
    check_output(args.out, MARKERS_DIR, args.overwrite)
    rig = load_calibration(calib, warn_units=False)
    detections, truth = simulated_capture(args.motion, rig, args.fps, args.duration, model, args.seed)
    with replacing(args.out, MARKERS_DIR) as out:
        write_marker_capture(out, rig, detections, truth)
    T, C, M = detections.uv.shape[:3]
    print(f"wrote {T} frames of {M} markers in {C} cameras to {args.out}")
    return 0


def run(args: argparse.Namespace) -> int:
    from torchtrack.checks import InputError
    from torchtrack.io.outputs import SEQUENCE_DIR, check_output
    from torchtrack.synth.markers import MarkerStyle
    from torchtrack.synth.scene import SceneConfig
    from torchtrack.synth.sequence import RigConfig, SynthConfig, is_current, write_sequence

    if args.kind == "markers":
        return run_markers(args)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 640x480, got {args.size!r}") from None
    markers = None
    if args.markers:
        try:
            colour = tuple(float(v) for v in args.marker_colour.split(","))
        except ValueError:
            raise InputError(f"--marker-colour must look like 0.95,0.1,0.75, got {args.marker_colour!r}") from None
        markers = MarkerStyle(radius_m=args.marker_radius, colour=colour)
    cfg = SynthConfig(
        motion=args.motion, duration_s=args.duration, starfish_s=args.starfish, fps=args.fps,
        subject_height_m=args.height, background_frames=args.background_frames, video_format=args.format,
        rig=RigConfig(num_cameras=args.cameras, width=w, height=h, radius_m=args.radius),
        scene=dataclasses.replace(SceneConfig(), noise_std=args.noise / 255.0,
                                  illumination_change=args.illumination_change, shadow=args.shadow,
                                  distractor=args.distractor, seed=args.seed),
        markers=markers, seed=args.seed)
    if args.reuse and is_current(args.out, cfg):
        print(f"{args.out} already holds this sequence (--reuse): kept")
        return 0
    check_output(args.out, SEQUENCE_DIR, args.overwrite or args.reuse)
    out = write_sequence(cfg, args.out, device=args.device)
    print(f"wrote synthetic sequence to {out}")
    return 0
