"""`torchtrack detect`: coloured markers in a sequence's video, labelled from one frame, to markers2d.npz."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("detect", help="find coloured ball markers in a video (markers2d.npz)",
                       description="Learn the balls' colour from one labelled frame, detect them in every frame of "
                                   "every view and link each view's detections to the labelled markers; writes "
                                   "SEQ/markers2d.npz for `torchtrack track SEQ --mode markers`.")
    p.add_argument("sequence", metavar="SEQ", help="sequence folder (calibration.toml, video/ or frames/)")
    p.add_argument("--labels", required=True, metavar="CSV",
                   help="one frame's labelled markers: a header frame,camera,marker,u,v and a row per marker and "
                        "view (`torchtrack synth --markers` writes SEQ/marker_labels.csv)")
    p.add_argument("--out", metavar="NPZ", help="where to write (default: SEQ/markers2d.npz)")
    p.add_argument("--threshold", type=float, default=3.0, metavar="SIGMAS",
                   help="a pixel is a marker's within this Mahalanobis distance of the learned colour "
                        "(default: %(default)s)")
    p.add_argument("--gate", type=float, default=15.0, metavar="PX",
                   help="a detection is a marker's candidate within this of where the marker is expected, pixels "
                        "(default: %(default)s)")
    p.add_argument("--candidates", type=int, default=3, metavar="K",
                   help="candidates kept per marker and view, the nearest first (default: %(default)s)")
    p.add_argument("--min-area", type=int, default=2, metavar="PX",
                   help="smallest detection in pixels (default: %(default)s)")
    p.add_argument("--max-area", type=int, default=2000, metavar="PX",
                   help="largest detection in pixels (default: %(default)s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    import numpy as np

    from torchtrack.checks import InputError
    from torchtrack.io.markers2d import save_markers2d
    from torchtrack.markers.detect import detect_sequence, read_marker_labels

    if args.candidates < 1 or args.gate <= 0 or args.threshold <= 0 or not 1 <= args.min_area <= args.max_area:
        raise InputError("detect: --candidates >= 1, --gate and --threshold > 0 and 1 <= --min-area <= "
                         "--max-area are needed")
    labels = read_marker_labels(args.labels)
    data = detect_sequence(args.sequence, labels, threshold=args.threshold, gate_px=args.gate,
                           candidates=args.candidates, min_area=args.min_area, max_area=args.max_area)
    out = Path(args.out) if args.out else Path(args.sequence) / "markers2d.npz"
    save_markers2d(data, out)
    seen = np.isfinite(data.uv[..., 0, 0]).mean()
    print(f"wrote {out}: {len(data.frame_index)} frames, {len(data.marker_names)} markers in "
          f"{len(data.camera_names)} cameras, a candidate for {seen:.0%} of markers and views")
    return 0
