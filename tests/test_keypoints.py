"""The keypoint start: multi-view triangulation against closed forms and OpenCV, the choice of views that see the
same person, the start fitted to a known pose's detections, and MediaPipe on the real Pose2Sim demo."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from tests.test_render import ring_rig
from torchtrack.checks import InputError
from torchtrack.keypoints.detector import KEYPOINTS, KeypointDetector, detector_available
from torchtrack.keypoints.start import KeypointStartConfig, start_from_keypoints
from torchtrack.keypoints.triangulate import consistent_views, nearest_to_rays, triangulate_keypoints
from torchtrack.skeleton import Skeleton

DEMO = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "pose2sim_demo"


def _rig(C=6, dist=None):
    """A ring of C 640x480 cameras 3 m from the centre (with lens distortion when given)."""
    return ring_rig(C=C, W=640, H=480, f=500.0, dist=dist)


def _points(n, gen):
    return torch.rand(n, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 1.0, 1.8]) - torch.tensor(
        [0.5, 0.5, 0.0])


def test_nearest_to_rays_recovers_points_through_distorted_cameras():
    gen = torch.Generator().manual_seed(0)
    rig = _rig(dist=torch.tensor([[-0.1, 0.02, 0.001, -0.001, 0.0]] * 6, dtype=torch.float64))
    X = _points(50, gen)
    uv, valid = rig.project(X)
    assert bool(valid.all())
    o, d = rig.pixel_rays(uv)
    Y = nearest_to_rays(o, d, torch.ones(6, 50, dtype=torch.float64))
    assert torch.allclose(Y, X, atol=1e-6)
    # one view alone leaves the depth unknown
    w = torch.zeros(6, 50, dtype=torch.float64)
    w[2] = 1
    assert bool(torch.isnan(nearest_to_rays(o, d, w)).all())


def test_two_view_triangulation_matches_opencv():
    gen = torch.Generator().manual_seed(1)
    rig = _rig(C=4)
    X = _points(20, gen)
    uv, _ = rig.project(X)
    noisy = uv + torch.randn(uv.shape, generator=gen, dtype=torch.float64) * 1.5
    w = torch.zeros(4, 20, dtype=torch.float64)
    w[0] = w[1] = 1
    ours = nearest_to_rays(*rig.pixel_rays(noisy), w)
    P = [(rig.K[c] @ torch.cat([rig.R_cam_world[c], rig.t_cam_world[c][:, None]], 1)).numpy() for c in (0, 1)]
    h = cv2.triangulatePoints(P[0], P[1], noisy[0].numpy().T, noisy[1].numpy().T)
    cv = (h[:3] / h[3]).T
    # the two minimise different errors (ray distance against algebraic), so they agree to the noise's scale
    assert np.abs(ours.numpy() - cv).max() < 0.01
    assert np.abs(ours.numpy() - X.numpy()).mean() < 0.01


def test_a_wrong_view_is_dropped_and_the_point_recovered():
    gen = torch.Generator().manual_seed(2)
    rig = _rig(C=6)
    X = _points(13, gen)
    uv, _ = rig.project(X)
    bad = uv.clone()
    bad[4, 5] += torch.tensor([60.0, -40.0], dtype=torch.float64)  # view 4 of keypoint 5 detected elsewhere
    conf = torch.ones(6, 13, dtype=torch.float64)
    tri = triangulate_keypoints(rig, bad, conf, max_error_px=5.0)
    assert torch.allclose(tri.points, X, atol=1e-6)
    assert not bool(tri.views[4, 5]) and int(tri.views.sum()) == 6 * 13 - 1
    # with only two views that disagree (off the epipolar line) the point is not made up
    o, d = rig.pixel_rays(uv)
    line, _ = rig.project(torch.stack([o[0, 5] + 2.0 * d[0, 5], o[0, 5] + 4.0 * d[0, 5]]))  # view 0's ray
    e = line[4, 1] - line[4, 0]
    off = uv.clone()
    off[4, 5] += 40.0 * torch.stack([-e[1], e[0]]) / e.norm()
    conf2 = torch.zeros(6, 13, dtype=torch.float64)
    conf2[[0, 4]] = 1
    two = triangulate_keypoints(rig, off, conf2, 5.0)
    assert bool(torch.isnan(two.points[5]).all()) and not bool(two.views[:, 5].any())
    assert torch.allclose(two.points[6], X[6], atol=1e-6)


def test_consistent_views_leave_out_a_bystander():
    gen = torch.Generator().manual_seed(3)
    rig = _rig(C=6)
    X = _points(13, gen)
    other = _points(13, gen) + torch.tensor([1.2, -0.8, 0.0], dtype=torch.float64)  # someone else
    uv, _ = rig.project(X)
    uv_other, _ = rig.project(other)
    mixed = uv.clone()
    mixed[[1, 4]] = uv_other[[1, 4]]  # two cameras' detector picked the bystander
    conf = torch.ones(6, 13, dtype=torch.float64)
    views = consistent_views(rig, mixed, conf, 5.0)
    assert views.tolist() == [True, False, True, True, False, True]
    tri = triangulate_keypoints(rig, mixed, conf * views[:, None], 5.0)
    assert torch.allclose(tri.points, X, atol=1e-6)
    # batched over frames: the second frame has no bystander
    both = torch.stack([mixed, uv], 1)  # (C, T, K, 2)
    views2 = consistent_views(rig, both, torch.ones(6, 2, 13, dtype=torch.float64), 5.0)
    assert views2[:, 0].tolist() == views.tolist() and bool(views2[:, 1].all())


class _ProjectingDetector(KeypointDetector):
    """Reports the projections of known keypoints (+ noise); the image's first pixel says camera and frame."""

    def __init__(self, rig, points, noise_px, gen):
        self.uv, _ = rig.project(points)  # (C, T, K, 2)
        self.uv = self.uv + torch.randn(self.uv.shape, generator=gen, dtype=self.uv.dtype) * noise_px
        self.calls = 0

    def detect(self, image_rgb):
        c, t = int(image_rgb[0, 0, 0]), int(image_rgb[0, 0, 1])
        self.calls += 1
        return self.uv[c, t].numpy(), np.ones(len(KEYPOINTS))


def _fake_folder(rig, num_frames=30, fps=30.0):
    def read_camera_frames(c, frames):
        images = np.zeros((len(frames), 4, 4, 3), np.uint8)
        images[:, 0, 0, 0] = c
        images[:, 0, 0, 1] = np.arange(len(frames))  # the t-th frame asked for
        return images, np.ones(len(frames), bool)
    return SimpleNamespace(num_cameras=len(rig), fps=fps, num_frames=num_frames, rig=rig,
                           read_camera_frames=read_camera_frames)


def test_start_from_keypoints_recovers_a_known_pose_and_body():
    gen = torch.Generator().manual_seed(4)
    generic = Skeleton.from_urdf()
    lengths = {b: float(L) * 1.08 for b, L in zip(generic.bone_names, generic.bone_lengths)}  # 8 % larger
    subject = generic.with_bone_lengths(lengths)
    pose = subject.starfish_angles()
    pose[:2] = torch.tensor([0.2, -0.1])  # a little off the centre
    pose[3] = 0.7  # turned
    pose[6:] += torch.randn(pose[6:].shape, generator=gen) * 0.15
    pose = subject.clamp(pose)
    frames = 6
    out = list(subject.output_names)
    truth = subject.forward(pose[None]).output_points[0].double()  # (J, 3)
    points = truth[[out.index(n) for n in KEYPOINTS]][None].expand(frames, -1, -1)  # a still subject
    rig = _rig(C=6)
    detector = _ProjectingDetector(rig, points, noise_px=1.0, gen=gen)
    cfg = KeypointStartConfig(frames=frames, span_s=0.5)
    found, why = start_from_keypoints(_fake_folder(rig), rig, Skeleton.from_urdf(), detector, cfg)
    assert found is not None, why
    assert detector.calls == 6 * frames and found.frames == [0, 3, 6, 9, 12, 15]
    got = found.skeleton.forward(found.angles[None]).output_points[0].double()
    idx = [list(found.skeleton.output_names).index(n) for n in KEYPOINTS]
    err = (got[idx] - truth[[out.index(n) for n in KEYPOINTS]]).norm(dim=-1)
    assert float(err.mean()) < 0.02, err
    assert abs(found.skeleton.height() - subject.height()) < 0.05


def test_no_consistent_person_in_the_start_frame_gives_no_start():
    gen = torch.Generator().manual_seed(5)
    rig = _rig(C=4)
    points = _points(13, gen)[None].expand(3, -1, -1)
    detector = _ProjectingDetector(rig, points, noise_px=0.0, gen=gen)
    detector.uv[1] += 80.0  # every camera sees something else: no two agree
    detector.uv[2] -= 80.0
    detector.uv[3, :, :, 0] += 120.0
    found, why = start_from_keypoints(_fake_folder(rig), rig, Skeleton.from_urdf(), detector,
                                      KeypointStartConfig(frames=3))
    assert found is None and "frame 0" in why and "camera" in why


def test_keypoint_start_config_names_bad_settings():
    with pytest.raises(InputError, match="unknown keypoint_start settings"):
        KeypointStartConfig.from_dict({"frame": 3})
    with pytest.raises(InputError, match="auto, on or off"):
        KeypointStartConfig(enabled="yes")
    assert KeypointStartConfig.from_dict({"enabled": False}).enabled == "off"  # YAML's bare off


@pytest.mark.skipif(not DEMO.is_dir(), reason="needs ../shared/data/pose2sim_demo")
@pytest.mark.skipif(not detector_available(), reason="needs MediaPipe (README, Install: the keypoint detector)")
def test_mediapipe_start_on_the_real_demo_lies_near_pose2sims_keypoints(tmp_path):
    from torchtrack.cameras.calib_io import load_calibration, write_native_toml
    from torchtrack.io.pose2sim import reference_landmarks
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.keypoints.detector import load_detector

    seq = tmp_path / "seq"
    (seq / "video").mkdir(parents=True)
    for v in sorted((DEMO / "videos").glob("cam*.mp4")):
        (seq / "video" / v.name).symlink_to(v.resolve())
    write_native_toml(load_calibration(DEMO / "calibration" / "Calib_qualisys_pose2sim.toml", warn_units=False),
                      seq / "calibration.toml")
    (seq / "meta.toml").write_text("fps = 60\n")
    folder = SequenceFolder(seq)
    found, why = start_from_keypoints(folder, folder.rig.float(), Skeleton.from_urdf(), load_detector(),
                                      KeypointStartConfig())
    assert found is not None, why
    assert len(found.cameras) == 4
    names, ref = reference_landmarks(DEMO)
    pts = found.skeleton.forward(found.angles[None]).output_points[0].numpy()
    out = list(found.skeleton.output_names)
    err = [np.linalg.norm(pts[out.index(n)] - ref[0, names.index(n)]) for n in names if n in out]
    # Pose2Sim's own keypoints come from another detector; the two agree to a few centimetres (docs/results.md
    # quotes the figure this prints: pytest -s)
    print(f"keypoint start on the real demo: frame 0 {1e3 * np.mean(err):.1f} mm from Pose2Sim's keypoints, a "
          f"{found.skeleton.height():.2f} m body fitted {1e3 * found.residual_m:.1f} mm from the triangulated ones")
    assert np.mean(err) < 0.07, np.round(err, 3)
    assert 1.6 < found.skeleton.height() < 1.9


def test_the_pipeline_uses_keypoints_on_small_rigs_only(monkeypatch):
    import torchtrack.keypoints.detector as det
    from torchtrack.tracking import pipeline

    gen = torch.Generator().manual_seed(6)
    rig = _rig(C=4)
    points = _points(13, gen)[None].expand(6, -1, -1)
    folder = _fake_folder(rig)
    folder.root = Path("seq")
    made = []

    def fake_detector(name="mediapipe"):
        made.append(name)
        return _ProjectingDetector(rig, points, 0.5, gen)

    monkeypatch.setattr(det, "load_detector", fake_detector)
    monkeypatch.setattr(det, "detector_available", lambda name="mediapipe": True)
    found = pipeline.keypoint_start(folder, KeypointStartConfig(), 0, None)  # random points: no body fits them
    assert found is None and made == ["mediapipe"]
    assert pipeline.keypoint_start(folder, KeypointStartConfig(max_cameras=3), 0, None) is None
    assert pipeline.keypoint_start(folder, KeypointStartConfig(enabled="off"), 0, None) is None
    assert made == ["mediapipe"]  # neither made a detector
    monkeypatch.setattr(det, "detector_available", lambda name="mediapipe": False)
    assert pipeline.keypoint_start(folder, KeypointStartConfig(), 0, None) is None  # auto: not installed


def test_the_start_picture_marks_used_and_dropped_detections():
    from torchtrack.keypoints.start import KeypointStart, draw_keypoint_start

    rig = _rig(C=2)  # 640x480
    small = rig.resized(320, 240)
    skel = Skeleton.from_urdf()
    uv = np.full((2, len(KEYPOINTS), 2), np.nan)
    uv[0, 0] = (100.0, 40.0)  # used, in camera 0
    uv[1, 3] = (500.0, 420.0)  # dropped, in camera 1
    used = np.zeros((2, len(KEYPOINTS)), bool)
    used[0, 0] = True
    angles = skel.rest_angles()
    angles[0] = 50.0  # the body far out of view: only the detections are drawn
    found = KeypointStart(angles, skel, 0, [0], 0.0, ["c0"], uv, used)
    out = draw_keypoint_start(torch.zeros(2, 3, 240, 320), small, found, np.array([[640, 480]] * 2))
    r = max(2, round(0.006 * 320))
    # the circles' rims at half the detections' coordinates: white for the used one, red for the dropped one
    assert out[0, :, 20, 50 + r].min() > 0.3
    assert out[1, 0, 210, 250 + r] > 0.3 and out[1, 1, 210, 250 + r] < 0.2
    assert float(out[1, :, 20, 50 + r].max()) == 0.0 and float(out[0, :, 210, 250 + r].max()) == 0.0


def test_a_keypoint_start_beside_a_second_person_is_not_used(caplog):
    """The detector sees one person per image, so cameras that agree on one of two people would start on them:
    the pipeline checks the start frame's voxels as the voxel start does, and uses the keypoint start only where
    they hold one person-sized part (two bodies 1.5 m apart: refused, with a warning naming the sequence; one:
    used)."""
    from conftest import voxelised_observation as _observation
    from torchtrack.blobs.model import BlobModel
    from torchtrack.tracking import pipeline
    from torchtrack.tracking.markerless import MarkerlessTracker
    from torchtrack.tracking.observation import VoxelObservation

    skel = Skeleton.from_urdf()
    subj, other = skel.scaled_to_height(1.7), skel.scaled_to_height(1.6)
    alone = _observation(subj, BlobModel.from_config(subj), subj.rest_angles())
    second = _observation(other, BlobModel.from_config(other), other.rest_angles(), shift=(0.0, 1.5, 0.0))
    both = VoxelObservation(*(torch.cat([getattr(alone, k), getattr(second, k)])
                              for k in ("points", "sizes", "weights", "colours")), alone.cameras_valid)
    batch = SimpleNamespace(images=torch.zeros(4, 3, 8, 8), valid=torch.ones(4, dtype=torch.bool))
    folder = SimpleNamespace(root=Path("seq_two"), iter_batches=lambda *a, **k: iter([batch]))
    tracker = MarkerlessTracker(skel)
    with caplog.at_level("WARNING", logger="torchtrack.tracking.pipeline"):
        assert not pipeline._one_person(folder, 0, lambda images, valid: [both], tracker, (8, 8), "cpu")
    assert "seq_two" in caplog.text and "separate person-sized parts" in caplog.text
    assert pipeline._one_person(folder, 0, lambda images, valid: [alone], tracker, (8, 8), "cpu")
