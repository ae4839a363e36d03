"""The colour marker detector and its labelling: chrominance against OpenCV, blob centres against drawn discs, the
linking against projected ground truth, and the whole `synth --markers` -> `detect` path against the
renderer's labelled pixels."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from conftest import demo_rig
from torchtrack.blobs import BlobModel
from torchtrack.checks import InputError
from torchtrack.cli import main
from torchtrack.io.markers2d import load_markers2d
from torchtrack.markers.detect import ChromaModel, _chroma, detect_blobs, link_detections, read_marker_labels
from torchtrack.skeleton import Skeleton
from torchtrack.synth.markers import marker_names, marker_positions, visible_centroids


def test_chroma_matches_opencv():
    import cv2

    gen = np.random.default_rng(0)
    rgb = gen.uniform(0.1, 1.0, size=(12, 16, 3)).astype(np.float32)
    ycrcb = cv2.cvtColor(rgb, cv2.COLOR_RGB2YCrCb)  # float: Y in [0, 1], Cr and Cb about 0.5
    ref = (ycrcb[..., 1:] - 0.5) / ycrcb[..., :1]  # (Cr, Cb) per unit luma
    ours = _chroma(torch.from_numpy(rgb).permute(2, 0, 1)).numpy()
    np.testing.assert_allclose(ours, ref, atol=2e-3)


def _disc_image(centres, radius, colour, gains, size=(120, 160), seed=0):
    """A textured background with discs of one colour under different light gains, supersampled edges."""
    H, W = size
    gen = np.random.default_rng(seed)
    img = np.clip(0.45 + 0.2 * gen.standard_normal((H, W, 3)), 0, 1)  # every hue, low saturation
    v, u = np.mgrid[0:H, 0:W]
    for (cu, cv), g in zip(centres, gains):
        inside = (u - cu) ** 2 + (v - cv) ** 2 <= radius ** 2
        img[inside] = np.asarray(colour) * g
    return torch.from_numpy(img).permute(2, 0, 1).float()


def test_detector_finds_shaded_discs_at_their_centres():
    """Discs lit from 0.4 to 1 (the per-unit-luma chrominance makes them one colour) on a noisy background of every
    hue: each found once at its centre, nothing else found; the model learned from a third of them."""
    centres = [(20.0, 20.0), (60.0, 30.0), (100.0, 25.0), (140.0, 40.0), (30.0, 90.0), (80.0, 80.0), (130.0, 95.0)]
    gains = [1.0, 0.4, 0.7, 0.55, 0.85, 0.45, 0.6]
    colour = (0.95, 0.1, 0.75)
    img = _disc_image(centres, 3.2, colour, gains)
    model = ChromaModel.fit(img[None], [torch.tensor(centres[:3])])
    found = detect_blobs(img[None], model, threshold=3.0)[0]
    assert len(found) == len(centres)
    d = np.linalg.norm(found[:, None] - np.asarray(centres)[None], axis=-1)
    assert d.min(0).max() < 0.05  # a disc's pixels are symmetric about its centre


def test_epipolar_cost_differentiates_with_respect_to_the_cameras():
    """The cost's in-place path is taken only where nothing asks for a gradient (a camera matrix may)."""
    from conftest import demo_rig
    from torchtrack.tracking.epipolar import epipolar_cost, fundamental_matrices, projection_matrices

    rig = demo_rig()
    P = projection_matrices(rig).double().clone().requires_grad_(True)
    points = torch.tensor([[[-0.9, -0.1, 1.0], [-0.7, 0.1, 1.3]]], dtype=torch.float64)
    det = torch.full((rig.num_cameras, 2, 1, 2), 600.0, dtype=torch.float64)
    F = fundamental_matrices(rig)
    with torch.enable_grad():  # other test modules turn gradients off for the whole session
        epipolar_cost(points, det, P, F, 1e6).sum().backward()
    h = 1e-6  # against central differences of the cost in two entries of P
    for idx in ((0, 0, 0), (1, 2, 3)):
        Pp, Pm = P.detach().clone(), P.detach().clone()
        Pp[idx] += h
        Pm[idx] -= h
        fd = (epipolar_cost(points, det, Pp, F, 1e6) - epipolar_cost(points, det, Pm, F, 1e6)).sum() / (2 * h)
        assert float(P.grad[idx]) == pytest.approx(float(fd), rel=1e-4, abs=1e-6)


def test_synth_reuse_sees_the_markers(tmp_path):
    from torchtrack.synth.markers import MarkerStyle
    from torchtrack.synth.sequence import SynthConfig, _synth_table

    plain, balls = SynthConfig(), SynthConfig(markers=MarkerStyle())
    assert _synth_table(plain) != _synth_table(balls)
    assert _synth_table(balls) != _synth_table(SynthConfig(markers=MarkerStyle(colour=(1.0, 0.85, 0.05))))


def test_labels_csv_errors_name_the_file_and_line(tmp_path):
    good = tmp_path / "labels.csv"
    good.write_text("frame,camera,marker,u,v\n3,cam0,LASI,10,20\n3,cam1,LASI,11.5,21\n", encoding="utf-8")
    labels = read_marker_labels(good)
    assert labels.frame == 3 and labels.points[("cam1", "LASI")] == (11.5, 21.0) and labels.markers == ["LASI"]
    np.testing.assert_array_equal(labels.pixels(["cam1", "cam9", "cam0"]), [[[11.5, 21.0]], [[np.nan] * 2], [[10, 20]]])
    cases = {"frame,camera,marker,u\n0,cam0,A,1\n": "lacks ['v']",
             "frame,camera,marker,u,v\n0,cam0,A,1,x\n": "line 2",
             "frame,camera,marker,u,v\n0,cam0,A,1,2\n1,cam0,B,1,2\n": "frames [0, 1]",
             "frame,camera,marker,u,v\n0,cam0,A,1,2\n0,cam0,A,3,4\n": "labelled twice",
             "frame,camera,marker,u,v\n": "no labelled markers"}
    for i, (text, words) in enumerate(cases.items()):
        bad = tmp_path / f"bad{i}.csv"
        bad.write_text(text, encoding="utf-8")
        with pytest.raises(InputError, match=re.escape(words)) as err:
            read_marker_labels(bad)
        assert str(bad) in str(err.value)


def test_synthetic_balls_rest_on_the_skin():
    """Each ball's centre lies one radius from its blob's surface and outside it: the distance to a dense sampling
    of the ellipsoid's surface (a plain reference, no normals) is the radius."""
    skel = Skeleton.from_urdf()
    blobs = BlobModel.from_config(skel)
    gen = torch.Generator().manual_seed(0)
    angles = 0.3 * (torch.rand(2, skel.num_dofs, generator=gen, dtype=torch.float64) - 0.5)
    centres, R = blobs.ellipsoids(skel(angles).bone_frames)
    r = 0.02
    balls = marker_positions(list(blobs.names), centres, R, blobs.semi_axes.double(), r)
    assert balls.shape == (2, len(marker_names()), 3)
    from torchtrack.synth.markers import _mirrored

    k = [list(blobs.names).index(p[1]) for p in _mirrored()]
    u, v = np.meshgrid(np.linspace(0, np.pi, 400), np.linspace(0, 2 * np.pi, 800), indexing="ij")
    sphere = np.stack([np.cos(u), np.sin(u) * np.cos(v), np.sin(u) * np.sin(v)], -1).reshape(-1, 3)
    for b in range(2):
        for m, blob in enumerate(k):
            a = blobs.semi_axes.double()[blob].numpy()
            surface = centres[b, blob].numpy() + (sphere * a) @ R[b, blob].numpy().T  # (S, 3) world
            p = balls[b, m].numpy()
            assert abs(np.linalg.norm(surface - p, axis=-1).min() - r) < 5e-4  # the sampling's spacing
            local = R[b, blob].numpy().T @ (p - centres[b, blob].numpy())
            assert ((local / a) ** 2).sum() > 1  # outside the blob


def test_visible_centroids_match_a_loop():
    gen = torch.Generator().manual_seed(3)
    parts = torch.randint(-1, 9, (2, 7, 9), generator=gen)
    uv, count = visible_centroids(parts, 5, 4)
    for c in range(2):
        for m in range(4):
            v, u = np.nonzero(parts[c].numpy() == 5 + m)
            assert count[c, m] == len(u)
            if len(u):
                np.testing.assert_allclose(uv[c, m].numpy(), [u.mean(), v.mean()])
            else:
                assert torch.isnan(uv[c, m]).all()


def test_linking_follows_identical_balls_through_occlusion_and_clutter():
    """Projected 3D markers on smooth paths, shuffled, with false detections and one marker hidden from one view
    for a while: every view's first candidate is the true marker wherever it is detected, also after it reappears
    (found again through the other views' triangulation)."""
    rig = demo_rig()
    gen = np.random.default_rng(0)
    T, M = 40, 6
    t = np.arange(T)[:, None, None] / 30.0
    base = np.array([-0.9, -0.1, 1.0]) + gen.uniform(-0.4, 0.4, size=(1, M, 3))
    X = base + 0.25 * np.sin(2.0 * t + gen.uniform(0, 6, size=(1, M, 3)))  # (T, M, 3) about 1 m/s at most
    uv, inside = rig.project(torch.from_numpy(X))
    uv, inside = uv.numpy(), inside.numpy()  # (C, T, M, 2)
    C = uv.shape[0]
    hidden = np.zeros((T, C, M), dtype=bool)
    hidden[10:20, 0, 2] = True
    blobs = []
    for f in range(T):
        frame = []
        for c in range(C):
            seen = uv[c, f][inside[c, f] & ~hidden[f, c]]
            false = gen.uniform([0, 0], rig.image_size_wh[c].numpy(), size=(2, 2))
            b = np.concatenate([seen, false])
            frame.append(b[gen.permutation(len(b))])
        blobs.append(frame)
    labels = np.where(inside[:, 0, :, None], uv[:, 0], np.nan)  # (C, M, 2)
    out = link_detections(blobs, labels, rig)  # (T, C, M, K, 2)
    truth = uv.transpose(1, 0, 2, 3)  # (T, C, M, 2)
    ok = inside.transpose(1, 0, 2) & ~hidden
    err = np.linalg.norm(out[..., 0, :] - truth, axis=-1)
    assert (err[ok] < 1e-3).all()
    assert not np.isfinite(out[10:20, 0, 2, 0]).all()  # hidden: never given another ball first


@pytest.fixture(scope="module")
def marker_video(tmp_path_factory):
    out = tmp_path_factory.mktemp("markers") / "seq"
    assert main(["synth", "--markers", "--out", str(out), "--duration", "0.6", "--starfish", "0.4",
                 "--background-frames", "2"]) == 0
    return out


def test_detector_against_the_labelled_pixels_of_its_synthetic_video(marker_video, capsys):
    """The must-show of the detector: on `synth --markers` video (mp4), the balls' visible-pixel centres of every
    frame (the renderer's labels) against the detections, and the linked candidates against the same labels."""
    from torchtrack.io.sequence import SequenceFolder

    gt = np.load(marker_video / "gt.npz")
    labels = read_marker_labels(marker_video / "marker_labels.csv")
    seq = SequenceFolder(marker_video)
    model = labels.colour_model(seq.read_frame(0), seq.camera_names)
    hits, errors, false = [], [], []
    for t in range(0, seq.num_frames, 5):
        found = detect_blobs(seq.read_frame(t), model)
        for c, b in enumerate(found):
            truth = gt["marker_uv"][t, c][gt["marker_pixels"][t, c] >= 4]
            r = np.sqrt(gt["marker_pixels"][t, c][gt["marker_pixels"][t, c] >= 4] / np.pi)
            near = np.linalg.norm(truth[:, None] - truth[None], axis=-1) + 1e9 * np.eye(len(truth))
            alone = near.min(1) > 4 * r  # balls that do not touch another in the image
            d = np.linalg.norm(truth[:, None] - b[None], axis=-1).reshape(len(truth), len(b))
            near = d.min(1) if len(b) else np.full(len(truth), np.inf)
            hits += list(near[alone] < 1.5)
            errors += list(near[alone][near[alone] < 1.5])
            false.append(int((d.min(0) > 6).sum()) if len(truth) else len(b))
    assert np.mean(hits) > 0.9 and np.mean(errors) < 0.8 and np.mean(false) < 4, (np.mean(hits), np.mean(errors),
                                                                                   np.mean(false))
    # the CLI's labelled candidates: the first is the ball wherever it shows
    assert main(["detect", str(marker_video), "--labels", str(marker_video / "marker_labels.csv")]) == 0
    data = load_markers2d(marker_video / "markers2d.npz")
    idx = [list(gt["marker_names"]).index(n) for n in data.marker_names]
    truth, seen = gt["marker_uv"][:, :, idx], gt["marker_pixels"][:, :, idx] >= 4
    first = np.linalg.norm(data.uv[..., 0, :] - truth, axis=-1) < 3
    assert first[seen].mean() > 0.85


def test_detect_markers_bad_labels(marker_video, tmp_path, capsys):
    bad = tmp_path / "labels.csv"
    for rows, words in (("0,camX,LASI,10,20", "cameras ['camX'] are not in"), ("999,cam0,LASI,10,20", "frame 999")):
        bad.write_text(f"frame,camera,marker,u,v\n{rows}\n", encoding="utf-8")
        assert main(["detect", str(marker_video), "--labels", str(bad), "--out", str(tmp_path / "m.npz")]) != 0
        assert words in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()


def test_marker_track_logs_what_it_saw_to_tensorboard(marker_video, tmp_path):
    """`track --mode markers` on the detected video: per-frame scalars, and each camera's frame with the detections
    drawn where markers2d.npz has them (white dots) and the model's markers as rings."""
    import io

    from PIL import Image
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    if not (marker_video / "markers2d.npz").is_file():
        assert main(["detect", str(marker_video), "--labels", str(marker_video / "marker_labels.csv")]) == 0
    out = tmp_path / "track"
    assert main(["track", str(marker_video), "--mode", "markers", "--out", str(out), "--stop", "6",
                 "--log-every", "5"]) == 0
    ea = EventAccumulator(str(out / "tb"), size_guidance={"images": 0})
    ea.Reload()
    assert {"markers/detected", "markers/particle_spread_mm", "markers/restarts",
            "markers/triangulated_error_mm"} <= set(ea.Tags()["scalars"])
    assert [e.step for e in ea.Scalars("markers/detected")] == list(range(6))
    data = load_markers2d(marker_video / "markers2d.npz")
    event = ea.Images("cameras/markers/cam0")[-1]
    image = np.asarray(Image.open(io.BytesIO(event.encoded_image_string)).convert("RGB"))
    uv = data.uv[event.step, 0].reshape(-1, 2)
    uv = uv[np.isfinite(uv).all(-1)]
    assert len(uv) > 5
    # white dots at the detections (each dot 5 px across; another marker's ring, 1 px wide, may cross its centre)
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    white = image.min(-1) > 200
    H, W = white.shape
    near = np.stack([white[np.clip(v + dv, 0, H - 1), np.clip(u + du, 0, W - 1)] for dv in (-1, 0, 1)
                     for du in (-1, 0, 1)], -1)
    assert near.any(-1).mean() > 0.9
