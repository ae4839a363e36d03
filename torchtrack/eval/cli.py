"""`torchtrack eval`: accuracy of a poses.npz against a reference (gt.npz): MPJPE per landmark, PCK, lost
frames; a table on stdout and optionally a JSON file."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> None:
    from torchtrack.conventions import LANDMARKS
    from torchtrack.eval.metrics import DEFAULT_PCK_THRESHOLDS_M

    p = sub.add_parser("eval", help="MPJPE, PCK and lost frames of a poses.npz against gt.npz",
                       description="Compare a predicted poses.npz with a reference in the same schema (such as "
                                   "the gt.npz of `torchtrack synth`) on their common frames and print MPJPE per "
                                   "landmark, root-aligned MPJPE, median and worst frame, PCK and lost frames "
                                   "(frames the prediction marks invalid, left out of the errors); with markers3d in "
                                   "both (marker mode), MMTA and MMTP of the markers.")
    p.add_argument("pred", type=Path, metavar="PRED", help="predicted poses.npz")
    p.add_argument("gt", type=Path, metavar="GT", help="reference poses in the same schema (gt.npz)")
    p.add_argument("--pck", type=float, nargs="+", default=list(DEFAULT_PCK_THRESHOLDS_M), metavar="M",
                   help=f"PCK thresholds in metres (default: {' '.join(f'{m:g}' for m in DEFAULT_PCK_THRESHOLDS_M)})")
    p.add_argument("--landmarks", nargs="+", default=None, metavar="NAME",
                   help=f"joints to evaluate (default: the 16 landmarks {', '.join(LANDMARKS)})")
    p.add_argument("--root", default="pelvis", metavar="NAME",
                   help="joint subtracted for the root-aligned MPJPE (default: %(default)s)")
    p.add_argument("--marker-threshold", type=float, default=0.05, metavar="M",
                   help="where both files have markers3d (marker mode): MMTA's threshold in metres, a marker "
                        "within it matches; MMTP is the matched markers' mean error (default: %(default)s)")
    p.add_argument("--json", type=Path, default=None, metavar="FILE",
                   help="also write the report as JSON to FILE: a new file, or an earlier report (with "
                        "--overwrite) (default: stdout only)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier report at --json FILE (default: refuse)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from torchtrack.eval.metrics import evaluate
    from torchtrack.io.atomic import write_text_atomic
    from torchtrack.io.outputs import JSON_REPORT, check_output
    from torchtrack.io.poses import load_poses

    if args.json is not None:
        check_output(args.json, JSON_REPORT, args.overwrite, "--json")  # before any work
    pred, truth = load_poses(args.pred), load_poses(args.gt)
    report = evaluate(pred, truth, landmarks=args.landmarks, pck_thresholds_m=args.pck, root=args.root,
                      pred_name=str(args.pred), truth_name=str(args.gt), marker_threshold_m=args.marker_threshold)
    print(f"{args.pred} vs {args.gt}")
    print(report.format())
    if args.json is not None:
        doc = {"pred": str(args.pred), "gt": str(args.gt), **report.to_dict()}
        write_text_atomic(args.json, json.dumps(doc, indent=2, allow_nan=False) + "\n")
        print(f"wrote {args.json}")
    return 0
