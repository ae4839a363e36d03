"""``torchtrack calib``: convert calibration files to torchtrack's native TOML, or show one.

    torchtrack calib convert IN OUT [--translation-scale S]
    torchtrack calib show FILE
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

import torch

from torchtrack.checks import InputError

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``calib`` with its actions ``convert`` and ``show``."""
    parser = subparsers.add_parser("calib", help="calibration files: `calib convert IN OUT`, `calib show FILE`",
                                   description="Convert calibration files to torchtrack's native TOML (or "
                                               "EasyMocap YAML), or show one.")
    actions = parser.add_subparsers(dest="calib_action", required=True, metavar="ACTION")

    convert = actions.add_parser(
        "convert", help="convert a calibration file to native TOML or EasyMocap YAML",
        description="Convert a calibration (native/anipose/Pose2Sim TOML, caliscope, Qualisys .qca, EasyMocap "
                    "YAML) to native TOML (OUT.toml) or EasyMocap YAML (OUT folder or OUT/intri.yml).")
    convert.add_argument("input", type=Path, metavar="IN", help="calibration file (or EasyMocap folder)")
    convert.add_argument("output", type=Path, metavar="OUT",
                         help="OUT.toml, or a folder / .yml path for EasyMocap YAML")
    convert.add_argument("--translation-scale", type=float, default=1.0, metavar="FACTOR",
                         help="multiply translations by FACTOR, e.g. 0.001 for a rig calibrated in mm "
                              "(default: %(default)s)")
    convert.add_argument("--overwrite", action="store_true",
                         help="replace an existing calibration file at OUT (default: refuse)")
    convert.set_defaults(func=run_convert)

    show = actions.add_parser("show", help="print the cameras: sizes, focal lengths, centres",
                              description="Print one line per camera: name, model, image size (pixels), focal "
                                          "lengths and principal point (pixels), centre in world coordinates.")
    show.add_argument("file", type=Path, metavar="FILE", help="calibration file (any supported format)")
    show.set_defaults(func=run_show)


def _scaled(rig, scale: float):
    from torchtrack.cameras.rig import CameraRig

    if not (math.isfinite(scale) and scale > 0):
        raise InputError(f"--translation-scale must be a positive finite number, got {scale}")
    if scale == 1.0:
        return rig
    return CameraRig(rig.names, rig.K, rig.R_cam_world, rig.t_cam_world * scale, rig.image_size_wh, rig.dist,
                     rig.fisheye)


def run_convert(args: argparse.Namespace) -> int:
    """Read ``args.input`` (float64, any format), scale translations, write ``args.output``."""
    from torchtrack.cameras.calib_formats import write_easymocap_yaml
    from torchtrack.cameras.calib_io import check_translation_units, load_calibration, write_native_toml
    from torchtrack.io.outputs import CALIBRATION_FILE, EASYMOCAP_FILE, check_output

    out: Path = args.output
    suffix = out.suffix.lower()
    if suffix == ".toml":
        check_output(out, CALIBRATION_FILE, args.overwrite, "OUT")
    elif suffix in (".yml", ".yaml", "") or out.is_dir():
        folder = out.parent if suffix in (".yml", ".yaml") else out
        for name in ("intri.yml", "extri.yml"):
            check_output(folder / name, EASYMOCAP_FILE, args.overwrite, "OUT")
    else:
        raise InputError(f"{out}: unknown output format (use .toml for native TOML, a folder for EasyMocap YAML)")
    rig = _scaled(load_calibration(args.input, dtype=torch.float64, warn_units=False), args.translation_scale)
    try:  # kept as asked (a rig may be in mm on purpose), but tracking needs metres: say so
        check_translation_units(rig, f"{args.input} with --translation-scale {args.translation_scale:g}")
    except InputError:
        far = float(rig.centers().double().norm(dim=-1).max())
        log.warning("%s with --translation-scale %g: a camera is %s units from the world origin; tracking needs "
                    "metres (a sequence folder refuses cameras more than 100 m away): --translation-scale %g would "
                    "give metres if these are millimetres", args.input, args.translation_scale, f"{far:,.0f}",
                    args.translation_scale * 0.001)
    if suffix == ".toml":
        write_native_toml(rig, out)
        written = [out]
    else:
        written = list(write_easymocap_yaml(rig, folder))
    print(f"wrote {len(rig)} cameras to {', '.join(str(p) for p in written)}")
    return 0


def run_show(args: argparse.Namespace) -> int:
    """Print one line per camera: name, model, size, focal lengths, principal point, centre."""
    from torchtrack.cameras.calib_io import check_translation_units, detect_format, load_calibration

    rig = load_calibration(args.file, dtype=torch.float64, warn_units=False)
    print(f"{args.file}: {detect_format(args.file)} calibration, {len(rig)} cameras")
    try:
        check_translation_units(rig, str(args.file))
    except InputError as exc:
        log.warning("%s", exc)
    centres = rig.centers().tolist()
    for i, name in enumerate(rig.names):
        K = rig.K[i].tolist()
        w, h = rig.image_size_wh[i].tolist()
        model = "fisheye" if rig.fisheye[i] else "pinhole"
        cx, cy, cz = centres[i]
        print(f"  {name:<12} {model:<7} {w}x{h}  f=({K[0][0]:.2f}, {K[1][1]:.2f})  c=({K[0][2]:.2f}, "
              f"{K[1][2]:.2f})  centre=({cx:.4g}, {cy:.4g}, {cz:.4g})  dist={[round(d, 6) for d in rig.dist[i].tolist()]}")
    return 0
