#!/usr/bin/env python
"""Build the start search's prior over real human poses (``configs/pose_prior.npz``) from the captures in
``../shared/data/mocap``.

Every capture that retargets onto our skeleton (the CMU BVH files; the C3D files whose markers give the joint
centres, :mod:`torchtrack.synth.c3d_motion`) is sampled at --fps; each pose, root translation and heading zeroed
(the tilt kept), is added with its left-right mirror; farthest-point sampling on the template's landmarks (root
relative, mean distance) then keeps poses until every sampled pose lies within --cover-mm of a kept one (at most
--max-poses). Each kept pose records its capture, so that an evaluation can leave a subject's own poses out
(``TrackerConfig.start_prior_exclude``).

    .venv/bin/python scripts/build_pose_prior.py            # writes configs/pose_prior.npz
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import torch

from torchtrack.checks import InputError
from torchtrack.conventions import LANDMARKS
from torchtrack.io.atomic import atomic_path
from torchtrack.resources import CONFIG_DIR
from torchtrack.skeleton import Skeleton
from torchtrack.synth.bvh_motion import retarget_bvh
from torchtrack.synth.c3d_motion import retarget_c3d
from torchtrack.tracking.poses import mirrored

MOCAP = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap"
ROOT_ZEROED = ("root_tx", "root_ty", "root_tz", "root_rz")


def capture_poses(path: Path, template: Skeleton, fps: float) -> torch.Tensor:
    """(T, D) the capture's poses on the template's DOFs, root translation and heading zeroed."""
    result = retarget_bvh(path, template, fps) if path.suffix == ".bvh" else retarget_c3d(path, template, fps)
    angles = result.angles.clone()
    for name in ROOT_ZEROED:
        angles[:, template.dof_names.index(name)] = 0.0
    return template.clamp(angles)


def descriptor(template: Skeleton, angles: torch.Tensor) -> torch.Tensor:
    """(N, L, 3) the template's landmarks relative to its pelvis, for pose distances."""
    idx = [list(template.output_names).index(n) for n in LANDMARKS]
    pts = template.forward(angles).output_points[:, idx]
    return pts - pts[:, :1]


def farthest_points(x: torch.Tensor, cover_m: float, limit: int) -> tuple[list[int], float]:
    """Indices of ``x (N, L, 3)`` kept by farthest-point sampling (mean landmark distance) until every pose is
    within ``cover_m`` of a kept one or ``limit`` are kept; and the cover reached (m)."""
    keep = [0]
    dist = (x - x[0]).norm(dim=-1).mean(-1)
    while len(keep) < limit and float(dist.max()) > cover_m:
        i = int(dist.argmax())
        keep.append(i)
        dist = torch.minimum(dist, (x - x[i]).norm(dim=-1).mean(-1))
    return keep, float(dist.max())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mocap", type=Path, default=MOCAP, help="folder searched for *.bvh and *.c3d (default: "
                    "../shared/data/mocap)")
    ap.add_argument("--fps", type=float, default=10.0, help="poses sampled per second of capture (default: 10)")
    ap.add_argument("--cover-mm", type=float, default=60.0,
                    help="every sampled pose within this mean landmark distance of a kept one (default: 60 mm)")
    ap.add_argument("--max-poses", type=int, default=160, help="at most this many poses kept (default: 160)")
    ap.add_argument("--out", type=Path, default=CONFIG_DIR / "pose_prior.npz")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    template = Skeleton.from_urdf()
    poses, sources = [], []
    for path in sorted(args.mocap.rglob("*.bvh")) + sorted(args.mocap.rglob("*.c3d")):
        try:
            a = capture_poses(path, template, args.fps)
        except (InputError, KeyError, ValueError) as exc:  # no joint centres in this marker set, or malformed
            print(f"skipped {path.relative_to(args.mocap)}: {str(exc).split(': ', 1)[-1][:100]}...")
            continue
        a = torch.cat([a, mirrored(template, a)])
        poses.append(a)
        sources += [path.stem] * a.shape[0]
        print(f"{path.relative_to(args.mocap)}: {a.shape[0] // 2} poses (and their mirrors)")
    if not poses:
        raise SystemExit(f"no capture under {args.mocap} could be retargeted")
    angles = torch.cat(poses)
    with torch.no_grad():
        keep, cover = farthest_points(descriptor(template, angles), args.cover_mm / 1e3, args.max_poses)
    kept_sources = np.asarray([sources[i] for i in keep])
    names, counts = np.unique(kept_sources, return_counts=True)
    print(f"kept {len(keep)} of {angles.shape[0]} poses, each within {1e3 * cover:.0f} mm of a kept one; "
          + ", ".join(f"{n} {c}" for n, c in zip(names, counts)))

    with atomic_path(args.out) as tmp:
        np.savez_compressed(tmp, angles=angles[keep].float().numpy(), dof_names=np.asarray(template.dof_names),
                            source=kept_sources)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
