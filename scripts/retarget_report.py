#!/usr/bin/env python
"""Print how closely the retargeted skeleton follows each CMU BVH file (landmark distance after retargeting)
and its proportions against the template scaled to the same height (what one height scale cannot represent) and
as fractions of its height against Winter's anthropometric tables.

Usage: .venv/bin/python scripts/retarget_report.py [BVH ...] [--fps 30]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from torchtrack.skeleton import Skeleton
from torchtrack.synth.bvh_motion import retarget_bvh

PROPORTION_BONES = ("torso", "head", "l_upperarm", "l_forearm", "l_thigh", "l_shank")
DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap" / "cmu"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path, default=sorted(DATA.glob("*.bvh")))
    ap.add_argument("--fps", type=float, default=30.0)
    args = ap.parse_args()
    for path in args.files:
        res = retarget_bvh(path, Skeleton.from_urdf(), args.fps)
        r = res.residual_m * 1000
        print(f"{path.name}: {r.shape[0]} frames at {args.fps:g} fps, subject height {res.skeleton.height():.3f} m, "
              f"joint distance mean {r.mean():.1f} mm, median {r.median():.1f} mm, max {r.max():.1f} mm")
        for i, name in enumerate(res.joint_names):
            print(f"    {name:12s} mean {r[:, i].mean():6.1f} mm   max {r[:, i].max():6.1f} mm")
        ours = res.skeleton.proportions()
        template = Skeleton.from_urdf().scaled_to_height(ours["height"]).proportions()
        print("  proportions vs the template at the same height: " + ", ".join(
            f"{b} {ours[b]:.3f} m ({ours[b] / template[b]:.2f}x)" for b in PROPORTION_BONES)
            + f"; neck above the shoulders {100 * ours['neck_above_shoulders']:+.1f} cm "
              f"(template {100 * template['neck_above_shoulders']:+.1f} cm)")
        body, H = res.skeleton, res.skeleton.height()
        z = body.rest_frames[body.frame_index(["l_upperarm", "l_thigh", "l_toe"])][:, 2, 3]
        print(f"  as fractions of the height (Winter's segment tables in brackets): shoulder joints "
              f"{float(z[0] - z[2]) / H:.3f} (0.818), hips {float(z[1] - z[2]) / H:.3f} (0.530), thigh + shank "
              f"{(ours['l_thigh'] + ours['l_shank']) / H:.3f} (0.491)")


if __name__ == "__main__":
    main()
