#!/usr/bin/env python
"""Occupancy on the real Pose2Sim demo: reference keypoints near occupied voxels, and phantom components.

The background is estimated from the moving sequence (there are no empty frames), with the subject's static
parts painted out (``BackgroundConfig.fill_static_subject``; ``--no-fill`` to leave them). For every frame: the
share of Pose2Sim's 21 reference keypoints that lie within --radius of an occupied voxel (P > 0.5), and the
connected components of occupied voxels that hold no keypoint (the operator standing in the background of
cam01/cam02 must not become one of human size). Writes a picture of the voxels projected on the four views, and
one of the keypoints missed in the frames under 90 %: each missed keypoint's surroundings in the four views, the
occupied voxels drawn over them, so whether the reference or the voxels are off can be seen.
The keypoints are Pose2Sim's raw triangulation, or with ``--filtered-reference`` its filtered output
(:data:`torchtrack.io.pose2sim.REFERENCE_FILTERED`), whose single-frame outliers are smoothed away;
``--reference-noise`` prints how the two differ. ``--limb-centroids`` prints where along each limb of the
reference its occupied voxels centre (the blobs' ``offset`` in configs/blobs.yaml is that fraction).

The defaults (frames at half the videos' size, 1 cm voxels, a 1 x 1 window) keep thin parts (toes, the head's
top) within 5 cm; at a quarter size, 2 cm voxels and a 3 x 3 window (``--scale 0.25 --voxel 0.02 --window 3``)
those parts are missed more often (docs/results.md, "Occupancy").

The grid's box is the floor region three cameras see (:func:`grid_from_rig` with ``min_views=3``; its box is
conservative, the one for four cuts the swinging foot in some frames), and voxels that fewer than
``--min-views`` (default 4) cameras see are unobserved: the Bayesian fusion has no veto from a camera that does
not see a voxel, so where only three cameras see, the operator (in cam_02) crossed with the subject's
silhouettes in two other views makes a human-sized phantom (with ``--min-views 3``), while every reference
keypoint of every frame projects into all four images.

``--background-from-track POSES`` takes the background from the frames each pixel is clearest of a track's body
instead (:func:`torchtrack.tracking.refine.background_from_track`; a track of the demo with its body, e.g.
``eval_pose2sim_tracking.py --init-from-reference --save-poses POSES``); ``--refine FIELD=VALUE`` overrides the
config's ``background_refinement`` settings it uses (``near_fraction=0.02``: pixels that stay near the tracked body
keep the plain estimate, its fill, which gives the stance foot's toes back; docs/results.md, "Occupancy").

Usage: .venv/bin/python scripts/eval_pose2sim_occupancy.py [--scale 0.5] [--voxel 0.01] [--window 1] [--min-views 4]
       [--picture JPG] [--misses JPG] [--no-fill] [--fill-prior-log-odds 0] [--background-from-track POSES
       [--refine near_fraction=0.02]] [--filtered-reference] [--reference-noise]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from torchtrack.background import BackgroundConfig, BackgroundModel
from torchtrack.cameras import load_calibration
from torchtrack.checks import InputError, with_overrides
from torchtrack.io.pose2sim import pose2sim_sequence, reference_keypoints
from torchtrack.io.poses import load_poses
from torchtrack.io.sequence import SequenceFolder
from torchtrack.occupancy import BayesConfig, BayesianGrid, grid_from_rig
from torchtrack.tracking.pipeline import load_config
from torchtrack.tracking.refine import RefineConfig, background_from_track

DEMO = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "pose2sim_demo"


def jitter_mm(points: np.ndarray) -> float:
    """(T, K, 3) m -> the RMS over frames and keypoints of the second difference along time (mm a frame^2): the
    frame-to-frame noise of a trajectory (0 for one that moves at constant velocity)."""
    return 1e3 * float(np.sqrt((np.diff(points, 2, axis=0) ** 2).sum(-1).mean()))


def reference_noise(demo: Path) -> None:
    """``--reference-noise``: Pose2Sim's raw triangulation against its filtered output: each one's jitter, how far
    apart they are, and the keypoint and frame where they are farthest apart."""
    names, raw = reference_keypoints(demo)
    _, filt = reference_keypoints(demo, filtered=True)
    apart = 1e3 * np.linalg.norm(raw - filt, axis=-1)  # (T, K) mm
    t, k = np.unravel_index(int(apart.argmax()), apart.shape)
    print(f"Pose2Sim's keypoints, raw / filtered: jitter (RMS second difference) {jitter_mm(raw):.1f} / "
          f"{jitter_mm(filt):.1f} mm a frame; apart by {apart.mean():.1f} mm on average, at most {apart[t, k]:.0f} "
          f"mm ({names[k]}, frame {t})")


def components_without_keypoints(occ: np.ndarray, keypoint_voxels: np.ndarray, voxel: float) -> list[float]:
    """Bounding-box diagonals (m) of the 26-connected components that contain no keypoint voxel."""
    labels, _ = ndimage.label(occ, structure=np.ones((3, 3, 3)))
    with_kp = set(np.unique(labels.reshape(-1)[keypoint_voxels]).tolist())
    out = []
    for lab, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is not None and lab not in with_kp:
            out.append(float(np.linalg.norm([s.stop - s.start for s in sl]) * voxel))
    return out


#: Segments between Pose2Sim's keypoints that outline the body: a voxel farther than ``--body-radius`` from all of
#: them is outside the body (limbs and trunk sides are covered; the radius allows for the reference's error).
BODY_SEGMENTS = [("RHip", "RKnee"), ("RKnee", "RAnkle"), ("RAnkle", "RBigToe"), ("RAnkle", "RHeel"),
                 ("LHip", "LKnee"), ("LKnee", "LAnkle"), ("LAnkle", "LBigToe"), ("LAnkle", "LHeel"),
                 ("LHip", "RHip"), ("LShoulder", "LHip"), ("RShoulder", "RHip"), ("Neck", "LShoulder"),
                 ("Neck", "RShoulder"), ("LShoulder", "LElbow"), ("LElbow", "LWrist"), ("RShoulder", "RElbow"),
                 ("RElbow", "RWrist"), ("Neck", "Head"), ("Head", "Nose"), ("Neck", "LHip"), ("Neck", "RHip")]


def project_on_segments(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``points (N, 3)`` on each segment ``a (S, 3) -> b (S, 3)``: (N, S) the nearest point's position along
    the segment as a fraction from ``a`` (clamped to [0, 1]), and (N, S) the distance to it."""
    ab = b - a  # (S, 3)
    t = np.einsum("nsk,sk->ns", points[:, None] - a[None], ab) / np.maximum((ab * ab).sum(-1), 1e-12)
    t = np.clip(t, 0, 1)
    return t, np.linalg.norm(points[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1)


def distance_to_segments(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) distance of each of ``points (N, 3)`` to the nearest of the segments ``a (S, 3) -> b (S, 3)``."""
    return project_on_segments(points, a, b)[1].min(1)


#: --limb-centroids: a voxel counts for a segment within this distance (m).
LIMB_RADIUS_M = 0.12
#: --limb-centroids: the limbs (proximal, distal keypoint) whose voxels' centroid is printed.
LIMBS = [("RHip", "RKnee"), ("RKnee", "RAnkle"), ("LHip", "LKnee"), ("LKnee", "LAnkle"), ("RShoulder", "RElbow"),
         ("RElbow", "RWrist"), ("LShoulder", "LElbow"), ("LElbow", "LWrist")]


def centroid_along_segments(points: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """(S,) where the centroid of each segment's points lies along it, as a fraction from ``a`` (0) to ``b`` (1);
    NaN for a segment with none. A point of ``points (N, 3)`` belongs to the nearest of the segments
    ``a (S, 3) -> b (S, 3)`` if within ``radius`` of it; its position along the segment is clamped to [0, 1]."""
    t, dist = project_on_segments(points, a, b)  # (N, S) each
    nearest = dist.argmin(1)  # (N,)
    rows = np.arange(len(points))
    mine = dist[rows, nearest] <= radius  # (N,) within the radius of its nearest segment
    count = np.bincount(nearest[mine], minlength=len(a))  # (S,)
    total = np.bincount(nearest[mine], weights=t[rows, nearest][mine], minlength=len(a))  # (S,)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def voxel_views(folder: SequenceFolder, rig, centres: torch.Tensor, t: int) -> list[np.ndarray]:
    """The four views of frame ``t`` at the rig's size as BGR uint8 images, the occupied voxel centres
    ``(N, 3)`` projected and painted green over them (each centre's pixel grown by one: 1 cm voxels at half size
    are about 3 px apart)."""
    import cv2

    W, H = (int(v) for v in rig.image_size_wh[0])
    img = folder.read_frame(t, size_wh=(W, H))  # (C, 3, H, W)
    uv, valid = rig.project(centres)  # (C, N, 2), (C, N)
    tiles = []
    for c in range(rig.num_cameras):
        tile = np.ascontiguousarray((img[c].permute(1, 2, 0).numpy() * 255).astype(np.uint8)[..., ::-1])
        px = uv[c][valid[c]].round().long().numpy()
        px = px[(px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)]
        mask = np.zeros((H, W), np.uint8)
        mask[px[:, 1], px[:, 0]] = 1
        mask = cv2.dilate(mask, np.ones((3, 3), np.uint8)).astype(bool)
        overlay = tile.copy()
        overlay[mask] = (40, 230, 40)
        tiles.append(cv2.addWeighted(overlay, 0.5, tile, 0.5, 0))
    return tiles


def picture(path: Path, folder: SequenceFolder, rig, centres: torch.Tensor, t: int) -> None:
    """The four views of frame ``t`` at the processing size with the occupied voxel centres drawn on them."""
    import cv2

    tiles = voxel_views(folder, rig, centres, t)
    for tile, name in zip(tiles, rig.names):
        cv2.putText(tile, name, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(tiles, axis=1), [cv2.IMWRITE_JPEG_QUALITY, 85])


def misses_picture(path: Path, folder: SequenceFolder, rig, voxels: list[torch.Tensor], names: list[str],
                   ref: np.ndarray, misses: list[tuple[int, list[str]]], half: int = 40, zoom: int = 3) -> None:
    """One row per missed keypoint of each frame in ``misses`` ((frame, names)): the four views' crops of 2 * half
    pixels square around its projection, the frame's occupied voxel centres (``voxels``, (N, 3) each) drawn in
    green, the other reference keypoints in blue and the missed one in red, enlarged ``zoom`` times."""
    import cv2

    W, H = (int(v) for v in rig.image_size_wh[0])
    rows = []
    for (t, missed), centres in zip(misses, voxels):
        views = [cv2.copyMakeBorder(v, half, half, half, half, cv2.BORDER_CONSTANT)  # crops off the image pad
                 for v in voxel_views(folder, rig, centres, t)]
        uv_kp, _ = rig.project(torch.from_numpy(ref[t]).float())  # (C, 21, 2)
        for name in missed:
            k = names.index(name)
            tiles = []
            for c, view in enumerate(views):
                u, v = uv_kp[c, k].tolist()
                u0, v0 = int(np.clip(round(u), 0, W)), int(np.clip(round(v), 0, H))  # a full crop even off the image
                crop = view[v0:v0 + 2 * half, u0:u0 + 2 * half]  # centred on the keypoint
                crop = cv2.resize(crop, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
                for j in range(len(names)):
                    x, y = ((uv_kp[c, j] - uv_kp[c, k]).numpy() + half) * zoom
                    if 0 <= x < crop.shape[1] and 0 <= y < crop.shape[0]:
                        cv2.circle(crop, (int(x), int(y)), 4, (0, 0, 255) if j == k else (255, 120, 0), -1)
                label = f"frame {t} {name} {rig.names[c]}"
                cv2.putText(crop, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
                tiles.append(crop)
            rows.append(np.concatenate(tiles, axis=1))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(rows, axis=0), [cv2.IMWRITE_JPEG_QUALITY, 85])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo", type=Path, default=DEMO)
    ap.add_argument("--scale", type=float, default=0.5, help="processing resolution relative to the videos")
    ap.add_argument("--voxel", type=float, default=0.01, help="voxel size (m)")
    ap.add_argument("--radius", type=float, default=0.05, help="a keypoint is covered within this of a voxel centre")
    ap.add_argument("--window", type=int, default=1, help="BayesConfig.window: k of the k x k sampling window")
    ap.add_argument("--fill-prior-log-odds", type=float, default=0.0,
                    help="BackgroundConfig.fill_prior_log_odds: prior log odds of room against subject in the fill")
    ap.add_argument("--body-radius", type=float, default=0.15,
                    help="voxels farther than this from every body segment between keypoints are outside the body")
    ap.add_argument("--min-views", type=int, default=4, help="voxels seen by fewer cameras are unobserved")
    ap.add_argument("--no-fill", action="store_true",
                    help="keep the subject's static parts in the estimated background (no fill_static_subject)")
    ap.add_argument("--background-from-track", type=Path, default=None, metavar="POSES",
                    help="re-estimate the background from the frames clearest of this track's body (a poses.npz of "
                         "the demo with its body, e.g. from eval_pose2sim_tracking.py --save-poses)")
    ap.add_argument("--filtered-reference", action="store_true",
                    help="score against Pose2Sim's filtered keypoints (its final output) instead of the raw "
                         "triangulation (torchtrack.io.pose2sim.REFERENCE_FILTERED)")
    ap.add_argument("--reference-noise", action="store_true",
                    help="print only how the raw triangulation and the filtered keypoints differ (jitter, distance, "
                         "the farthest keypoint); no video")
    ap.add_argument("--limb-centroids", action="store_true",
                    help="also print where along each limb of the reference (hip-knee, knee-ankle, shoulder-elbow, "
                         "elbow-wrist) its occupied voxels centre, as a fraction from the proximal keypoint: median "
                         "and quartiles over the frames; a voxel counts for the nearest of the body's segments, "
                         "within 12 cm")
    ap.add_argument("--refine", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="with --background-from-track: RefineConfig overrides of configs/markerless.yaml's "
                         "background_refinement section, e.g. near_fraction=0.01")
    ap.add_argument("--picture", type=Path, default=Path("docs/images/pose2sim_occupancy.jpg"),
                    help="the worst frame's voxels projected on the four views")
    ap.add_argument("--misses", type=Path, default=Path("docs/images/pose2sim_occupancy_misses.jpg"),
                    help="the keypoints missed in the frames under 90 %% (the worst four), in the four views")
    args = ap.parse_args()
    if args.refine and args.background_from_track is None:
        raise SystemExit("--refine changes the background from a track: give --background-from-track")
    if args.reference_noise:
        reference_noise(args.demo)
        return
    torch.set_grad_enabled(False)
    names, ref = reference_keypoints(args.demo, filtered=args.filtered_reference)  # (T, 21, 3)
    with tempfile.TemporaryDirectory() as tmp:
        seq = pose2sim_sequence(args.demo, Path(tmp) / "seq")
        full = load_calibration(seq / "calibration.toml")
        W, H = (int(round(float(v) * args.scale)) for v in full.image_size_wh[0])
        rig = full.resized(W, H)
        folder = SequenceFolder(seq, full)
        t0 = time.perf_counter()
        frames = torch.cat([b.images for b in folder.iter_batches(20, size_wh=(W, H))])  # (T, C, 3, H, W)
        bg_config = BackgroundConfig(fill_static_subject=not args.no_fill,
                                     fill_prior_log_odds=args.fill_prior_log_odds)
        if args.background_from_track is not None:
            try:
                config = load_config("markerless.yaml")
                refine = with_overrides(RefineConfig.from_dict(config["background_refinement"], config["source"]),
                                        args.refine, "--refine")
                bg = background_from_track(folder, load_poses(args.background_from_track), bg_config, refine,
                                           size_wh=(W, H), source=str(args.background_from_track))
            except InputError as e:
                raise SystemExit(str(e)) from None
            print(f"background re-estimated from the frames clearest of the track {args.background_from_track}")
        else:
            bg = BackgroundModel.from_sequence(frames, bg_config, camera_names=rig.names)
        spec = grid_from_rig(rig, args.voxel, min_views=3)
        grid = BayesianGrid(rig, spec, bg, BayesConfig(window=args.window, min_views=args.min_views))
        centres = spec.centres()
        shares, phantoms, hits, distances = [], [], [], []  # hits, distances: (T, 21) keypoint to nearest voxel
        volumes, outside = [], []  # occupied m^3 per frame; share of the occupied voxels outside the body
        seg = np.array([[names.index(p), names.index(q)] for p, q in BODY_SEGMENTS])
        limbs = np.array([BODY_SEGMENTS.index(limb) for limb in LIMBS])
        centroids = []  # (T, len(LIMBS)) with --limb-centroids
        for s in range(0, frames.shape[0], 10):
            occ = grid(frames[s:s + 10]).occupied()  # (b, V)
            for i in range(occ.shape[0]):
                t = s + i
                pts = centres[occ[i]].numpy()
                dist = cKDTree(pts).query(ref[t])[0] if len(pts) else np.full(len(names), np.inf)
                near = dist <= args.radius
                hits.append(near)
                distances.append(dist)
                volumes.append(len(pts) * args.voxel ** 3)
                if len(pts):
                    far = distance_to_segments(pts, ref[t][seg[:, 0]], ref[t][seg[:, 1]]) > args.body_radius
                    outside.append(float(far.mean()))
                if args.limb_centroids:  # every body segment competes for the voxels, the limbs' are kept
                    along = centroid_along_segments(pts, ref[t][seg[:, 0]], ref[t][seg[:, 1]], LIMB_RADIUS_M)
                    centroids.append(along[limbs])
                shares.append(float(near.mean()))
                kp_vox, inside = spec.index_of(torch.from_numpy(ref[t]).float())
                phantoms.append(components_without_keypoints(occ[i].reshape(spec.shape).numpy(),
                                                             kp_vox[inside].numpy(), args.voxel))
        elapsed = time.perf_counter() - t0
        shares_a = np.array(shares)
        largest = max((max(p) if p else 0.0) for p in phantoms)
        print(f"pose2sim_demo: {len(shares)} frames at {W}x{H}, grid {'x'.join(map(str, spec.shape))} of "
              f"{args.voxel} m, window {args.window}, min_views {args.min_views}; {elapsed:.1f} s")
        print(f"  keypoints within {args.radius * 100:.0f} cm of an occupied voxel: mean {shares_a.mean():.3f}, "
              f"worst frame {shares_a.min():.3f} (frame {int(shares_a.argmin())}), frames with >= 90 %: "
              f"{(shares_a >= 0.9).mean():.2f}")
        for t in np.flatnonzero(shares_a < 0.9):
            print(f"  frame {t} misses " + ", ".join(f"{names[k]} ({distances[t][k] * 100:.1f} cm)"
                                                     for k in np.flatnonzero(~hits[t])))
        print("  per keypoint over frames: " + ", ".join(
            f"{n} {v:.2f}" for n, v in zip(names, np.mean(hits, axis=0))))
        print(f"  largest component without a keypoint: {largest:.2f} m across")
        print(f"  occupied volume per frame: mean {np.mean(volumes):.3f} m^3 (a body is about 0.07), of which "
              f"{np.mean(outside):.2f} farther than {args.body_radius * 100:.0f} cm from every body segment")
        if args.limb_centroids:
            c = np.array(centroids)  # (T, len(LIMBS))
            print("  where each limb's voxels centre, from its proximal keypoint (median over frames, quartiles):")
            for k, (p, q) in enumerate(LIMBS):
                v = c[:, k][np.isfinite(c[:, k])]
                q1, med, q3 = np.percentile(v, [25, 50, 75]) if len(v) else (np.nan,) * 3
                print(f"    {p}-{q}: {med:.3f} ({q1:.3f}-{q3:.3f}), {len(v)} frames")
        t = int(shares_a.argmin())
        occ = grid(frames[t:t + 1]).occupied()[0]
        picture(args.picture, folder, rig, centres[occ], t)
        print(f"  wrote {args.picture} (frame {t})")
        worst = [int(t) for t in np.argsort(shares_a, kind="stable")[:4] if shares_a[t] < 0.9]
        if worst:
            misses = [(t, [names[k] for k in np.flatnonzero(~hits[t])]) for t in sorted(worst)]
            voxels = [centres[grid(frames[t:t + 1]).occupied()[0]] for t, _ in misses]
            misses_picture(args.misses, folder, rig, voxels, names, ref, misses)
            print(f"  wrote {args.misses} (frames {', '.join(str(t) for t, _ in misses)})")


if __name__ == "__main__":
    main()
