"""The marker tracker's sensitivity study (Canton-Ferrer §4.1, Fig. 6): MMTA and MMTP as the detector's misses,
false detections and pixel noise grow, and against the filter's particles and layers.

A real capture (default: the Plug-in-Gait walk) is seen by the real 4-camera rig of the Pose2Sim demo through the
simulated detector and tracked as `torchtrack track` does, one parameter varied at a time from the issue's
setting (p_miss 0.2, 0.1 false detections per view and frame, sigma 2 px, 500 particles, 5 layers). Prints a
table, writes OUT/sweep.png (one panel per parameter) and the curves to TensorBoard in OUT/tb.

    .venv/bin/python scripts/marker_sweep.py --out out/marker_sweep [--duration 1.5] [--quick]
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.cameras import load_calibration  # noqa: E402
from torchtrack.checks import InputError  # noqa: E402
from torchtrack.eval.metrics import evaluate  # noqa: E402
from torchtrack.io.outputs import script_work_folder  # noqa: E402
from torchtrack.logging import RunLogger  # noqa: E402
from torchtrack.markers.capture import MarkerScene, marker_scene, write_marker_capture  # noqa: E402
from torchtrack.markers.simulate import DetectorModel  # noqa: E402
from torchtrack.markers.track import track_markers  # noqa: E402
from torchtrack.tracking.particles import APFConfig  # noqa: E402

DATA = REPO.parent / "shared" / "data"
CAPTURE = DATA / "mocap" / "btk" / "c3d" / "PiG_Motion-FlatFoot-Full.c3d"
RIG = DATA / "pose2sim_demo" / "calibration" / "Calib_qualisys_pose2sim.toml"

#: parameter -> the values swept (the others at the issue's setting); --quick takes the first, middle and last.
SWEEPS = {"p_miss": (0.0, 0.2, 0.4, 0.6), "false_rate": (0.0, 0.5, 1.0, 2.0), "sigma_px": (0.5, 2.0, 4.0, 8.0),
          "particles": (100, 250, 500, 1000), "layers": (1, 3, 5, 8)}


def point(scene: MarkerScene, rig, detector: DetectorModel, apf: APFConfig) -> tuple[float, float]:
    """(MMTA, MMTP mm) of one setting on the capture placed in the rig; NaN where the subject cannot be fitted from
    the detections (the reason is printed)."""
    det, truth = scene.detections(detector, seed=0), scene.truth
    with tempfile.TemporaryDirectory() as tmp:
        folder = write_marker_capture(tmp, rig, det, truth)
        try:
            result = track_markers(folder, apf, progress=False)
        except InputError as exc:
            print(f"  no track: {str(exc).split(': ', 1)[-1][:150]}")
            return math.nan, math.nan
    m = evaluate(result.poses, truth).markers
    return m.mmta, m.mmtp_mm


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/marker_sweep"), help="folder of sweep.png and tb/")
    ap.add_argument("--capture", type=Path, default=CAPTURE, help="a C3D capture (default: the Plug-in-Gait walk)")
    ap.add_argument("--fps", type=float, default=30.0, help="frame rate the capture is resampled to (default: 30)")
    ap.add_argument("--duration", type=float, default=1.5, help="seconds of the capture (default: 1.5)")
    ap.add_argument("--params", nargs="+", default=list(SWEEPS), choices=list(SWEEPS))
    ap.add_argument("--quick", action="store_true", help="three values per parameter")
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    torch.set_num_threads(1)
    out = script_work_folder(args.out, "marker_sweep.py")
    rig = load_calibration(RIG, warn_units=False)
    base_det, base_apf = DetectorModel(p_miss=0.2, false_rate=0.1, sigma_px=2.0), APFConfig()
    fig, axes = plt.subplots(1, len(args.params), figsize=(4 * len(args.params), 3.4), squeeze=False)
    print(f"{'parameter':<11} {'value':>7} {'MMTA@50':>8} {'MMTP mm':>8}")
    scene = marker_scene(args.capture, rig, args.fps, args.duration, base_det.skin_m)  # retargeted once
    with RunLogger(out / "tb") as tb:
        for ax, name in zip(axes[0], args.params):
            values = SWEEPS[name]
            if args.quick:
                values = (values[0], values[len(values) // 2], values[-1])
            mmta, mmtp = [], []
            for i, v in enumerate(values):
                det = replace(base_det, **{name: v}) if hasattr(base_det, name) else base_det
                apf = replace(base_apf, **{name: v}) if hasattr(base_apf, name) else base_apf
                a, p = point(scene, rig, det, apf)
                mmta.append(100 * a)
                mmtp.append(p)
                print(f"{name:<11} {v:>7g} {100 * a:>7.2f}% {p:>8.1f}", flush=True)
                if math.isfinite(a):
                    tb.scalars(i, **{f"sweep/{name}/value": float(v), f"sweep/{name}/mmta_percent": 100 * a,
                                     f"sweep/{name}/mmtp_mm": p})
            ax.plot(values, mmta, "o-", color="tab:blue")
            ax.set_xlabel(name)
            ax.set_ylabel("MMTA@50 mm (%)", color="tab:blue")
            ax.set_ylim(min([50.0] + [v - 5 for v in mmta if math.isfinite(v)]), 100.5)
            twin = ax.twinx()
            twin.plot(values, mmtp, "s--", color="tab:red")
            twin.set_ylabel("MMTP (mm)", color="tab:red")
            twin.set_ylim(0, max([25.0] + [v + 5 for v in mmtp if math.isfinite(v)]))
    fig.suptitle(f"{args.capture.name}, {args.duration:g} s at {args.fps:g} frames/s, the Pose2Sim demo's rig")
    fig.tight_layout()
    fig.savefig(out / "sweep.png", dpi=110)
    print(f"wrote {out / 'sweep.png'} and TensorBoard logs in {out / 'tb'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
