"""Sequence folder reader: name matching, sizes, counts, batches, background, meta, real pose2sim layout."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from conftest import shared_data
from torchtrack.checks import InputError
from torchtrack.io.sequence import (DEFAULT_FPS, SequenceFolder, SequenceMeta, min_readable_cameras,
                                    normalise_camera_name, read_meta, tomllib)
from torchtrack.io.video import DataWarning, write_frames_png, write_video

H, W = 24, 32


def rig(names, sizes_wh=None):
    """Stand-in for CameraRig: the reader uses only ``names`` and ``image_size_wh`` (C, 2) [W, H]."""
    sizes_wh = sizes_wh if sizes_wh is not None else [[W, H]] * len(names)
    return SimpleNamespace(names=list(names), image_size_wh=torch.tensor(sizes_wh, dtype=torch.int64))


def frames(n: int, seed: int, h: int = H, w: int = W) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, h, w, 3), dtype=np.uint8)  # (n, h, w, 3)


def add_png(root: Path, name: str, data: np.ndarray, folder: str = "frames") -> Path:
    """Write an image-folder source; a meta.toml with the fps keeps image-only folders from warning about it."""
    write_frames_png(root / folder / name, data)
    if not (root / "meta.toml").exists():
        (root / "meta.toml").write_text("fps = 30.0\n")
    return root / folder / name


def as_images(data: np.ndarray) -> torch.Tensor:
    """(n, h, w, 3) uint8 -> (n, 3, h, w) float32 [0, 1]: the reference conversion."""
    return torch.from_numpy(data).permute(0, 3, 1, 2).float() / 255.0


def exact_on(device: torch.device) -> dict[str, float]:
    """assert_close tolerances for pixels converted on ``device`` against :func:`as_images`: exact on the CPU; on
    CUDA one float32 step at 1.0 (its division by a scalar multiplies by the reciprocal, which rounds differently)."""
    return {"rtol": 0.0, "atol": 0.0 if device.type == "cpu" else 2.0 ** -23}


@pytest.fixture
def two_cams(tmp_path):
    data = {"cam_a": frames(10, 1), "cam_b": frames(10, 2)}
    for name, d in data.items():
        add_png(tmp_path, name, d)
    return tmp_path, data


# ------------------------------------------------------------------------------------------------ batches


def test_batches_content_order_and_device(two_cams, device):
    root, data = two_cams
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    assert (seq.num_frames, len(seq), seq.num_cameras, seq.camera_names) == (10, 10, 2, ["cam_a", "cam_b"])
    batches = list(seq.iter_batches(3, device=device))
    assert [b.images.shape[0] for b in batches] == [3, 3, 3, 1]
    idx = torch.cat([b.frame_index for b in batches])
    assert idx.tolist() == list(range(10)) and idx.dtype == torch.int64
    images = torch.cat([b.images for b in batches])  # (10, 2, 3, H, W)
    valid = torch.cat([b.valid for b in batches])
    assert images.shape == (10, 2, 3, H, W) and images.dtype == torch.float32 and images.device.type == device.type
    assert valid.dtype == torch.bool and valid.shape == (10, 2) and bool(valid.all())
    for c, name in enumerate(["cam_a", "cam_b"]):
        torch.testing.assert_close(images[:, c].cpu(), as_images(data[name]), **exact_on(device))
    # a sub-range
    sub = list(seq.iter_batches(4, start=5, stop=8))
    assert [b.frame_index.tolist() for b in sub] == [[5, 6, 7]]
    torch.testing.assert_close(sub[0].images, images[5:8].cpu(), **exact_on(device))
    torch.testing.assert_close(seq.read_frame(7, device=device), images[7], rtol=0, atol=0)
    # every third frame from 1
    strided = list(seq.iter_batches(2, start=1, step=3))
    assert [b.frame_index.tolist() for b in strided] == [[1, 4], [7]]
    torch.testing.assert_close(torch.cat([b.images for b in strided]).cpu(), images[1::3].cpu(), rtol=0, atol=0)


def test_batches_bounded_decoding(two_cams):
    root, _ = two_cams
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    requested = []
    for src in seq.sources:
        original = src.read_indices

        def spy(indices, *, strict=True, _orig=original):
            indices = list(indices)
            requested.append(len(indices))
            return _orig(indices, strict=strict)

        src.read_indices = spy
    for _ in seq.iter_batches(4):
        pass
    assert requested and max(requested) <= 4 and sum(requested) == 2 * 10


def test_range_errors(two_cams):
    seq = SequenceFolder(two_cams[0], rig(["cam_a", "cam_b"]))
    with pytest.raises(InputError, match="outside"):
        next(seq.iter_batches(2, stop=11))
    with pytest.raises(InputError, match="batch_size"):
        next(seq.iter_batches(0))
    with pytest.raises(InputError, match="step"):
        next(seq.iter_batches(2, step=0))
    with pytest.raises(InputError, match="outside"):
        seq.read_frame(10)


def test_resize_matches_cv2_inter_area(two_cams):
    root, data = two_cams
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    batch = next(seq.iter_batches(2, size_wh=(16, 12)))
    assert batch.images.shape == (2, 2, 3, 12, 16)
    ref = np.stack([cv2.resize(f, (16, 12), interpolation=cv2.INTER_AREA) for f in data["cam_b"][:2]])
    torch.testing.assert_close(batch.images[:, 1], as_images(ref), rtol=0, atol=0)


def test_mp4_sequence(tmp_path):
    data = np.stack([np.full((48, 64, 3), 20 * i, np.uint8) for i in range(6)])  # flat grey levels
    for name in ("c1", "c2"):
        write_video(tmp_path / "video" / f"{name}.mp4", data, fps=50.0)
    seq = SequenceFolder(tmp_path, rig(["c1", "c2"], [[64, 48]] * 2))
    assert (seq.num_frames, seq.fps) == (6, 50.0)
    b = next(seq.iter_batches(6))
    assert bool(b.valid.all())
    err = (b.images[:, 0] - as_images(data)).abs()  # lossy codec on flat grey levels
    assert float(err.mean()) < 4 / 255 and float(err.max()) < 8 / 255  # measured 2.4 / 255 and 5 / 255


# ------------------------------------------------------------------------------------------------ names


def test_normalise_camera_name():
    assert normalise_camera_name("Cam_01") == "cam01" == normalise_camera_name("CAM-0-1".replace("-0-", "0"))
    assert normalise_camera_name("cam 02.left") == "cam02left"


def test_normalised_name_match_logged(tmp_path, caplog):
    write_video(tmp_path / "video" / "cam01.mp4", frames(3, 1), fps=30)
    add_png(tmp_path, "CAM-02", frames(3, 2))
    with caplog.at_level(logging.INFO, logger="torchtrack.io.sequence"):
        seq = SequenceFolder(tmp_path, rig(["cam_01", "cam_02"]))
    assert [s.path.name for s in seq.sources] == ["cam01.mp4", "CAM-02"]
    assert "cam_01" in caplog.text and "cam01.mp4" in caplog.text


def test_exact_name_wins_and_extras_warned(tmp_path):
    add_png(tmp_path, "cam_01", frames(3, 1))
    add_png(tmp_path, "cam01", frames(3, 2))
    with pytest.warns(DataWarning, match=r"without a calibrated camera.*cam01"):
        seq = SequenceFolder(tmp_path, rig(["cam_01"]))
    assert seq.sources[0].path.name == "cam_01"


def test_image_folder_preferred_over_video(tmp_path):
    write_video(tmp_path / "video" / "cam.mp4", frames(3, 1), fps=10)
    add_png(tmp_path, "cam", frames(3, 2))
    seq = SequenceFolder(tmp_path, rig(["cam"]))
    assert seq.sources[0].path == tmp_path / "frames" / "cam"


def test_missing_camera_message(tmp_path):
    add_png(tmp_path, "cam01", frames(2, 1))
    write_video(tmp_path / "video" / "side.mp4", frames(2, 2), fps=10)
    with pytest.raises(InputError) as e:
        SequenceFolder(tmp_path, rig(["cam_01", "cam_07"]))
    msg = str(e.value)
    assert "'cam_07'" in msg and str(tmp_path) in msg
    assert "video/side.mp4" in msg and "frames/cam01" in msg  # lists what was found


def test_ambiguous_normalised_match(tmp_path):
    add_png(tmp_path, "cam01", frames(2, 1))
    add_png(tmp_path, "CAM_01", frames(2, 2))
    with pytest.raises(InputError, match="several sources"):
        SequenceFolder(tmp_path, rig(["cam-01"]))


def test_missing_folder_and_calibration(tmp_path):
    with pytest.raises(InputError, match="not found"):
        SequenceFolder(tmp_path / "nope", rig(["a"]))
    with pytest.raises(InputError, match="calibration.toml"):
        SequenceFolder(tmp_path)


# ------------------------------------------------------------------------------------------------ sizes, counts


def test_padding_warning_and_edge_replication(tmp_path):
    small = frames(3, 5, h=H - 4, w=W - 6)  # decoded 26x20, calibrated 32x24
    add_png(tmp_path, "cam_p", small)
    add_png(tmp_path, "cam_q", frames(3, 6))
    with pytest.warns(DataWarning) as record:
        seq = SequenceFolder(tmp_path, rig(["cam_p", "cam_q"]))
    msgs = [str(r.message) for r in record if "edge replication" in str(r.message)]
    assert len(msgs) == 1
    assert "'cam_p'" in msgs[0] and "frames/cam_p" in msgs[0] and "26x20" in msgs[0] and "32x24" in msgs[0]
    img = seq.read_frame(1)[0]  # (3, H, W)
    ref = as_images(small)[1]  # (3, 20, 26)
    torch.testing.assert_close(img[:, :20, :26], ref, rtol=0, atol=0)
    torch.testing.assert_close(img[:, :20, 26:], ref[:, :, 25:26].expand(3, 20, 6), rtol=0, atol=0)
    torch.testing.assert_close(img[:, 20:], img[:, 19:20].expand(3, 4, W), rtol=0, atol=0)
    # resized output pads first, then resizes the calibrated-size picture
    padded = cv2.copyMakeBorder(small[1], 0, 4, 0, 6, cv2.BORDER_REPLICATE)
    ref_small = cv2.resize(padded, (16, 12), interpolation=cv2.INTER_AREA)
    torch.testing.assert_close(seq.read_frame(1, size_wh=(16, 12))[0], as_images(ref_small[None])[0], rtol=0, atol=0)


@pytest.mark.parametrize("decoded_wh", [(W + 4, H), (W - 20, H), (W, H - 17)])
def test_size_mismatch_is_an_error(tmp_path, decoded_wh):
    add_png(tmp_path, "cam_x", frames(2, 1, h=decoded_wh[1], w=decoded_wh[0]))
    with pytest.raises(InputError) as e:
        SequenceFolder(tmp_path, rig(["cam_x"]))
    msg = str(e.value)
    assert "'cam_x'" in msg and "frames/cam_x" in msg
    assert f"decoded {decoded_wh[0]}x{decoded_wh[1]}" in msg and f"calibrated {W}x{H}" in msg


@pytest.mark.parametrize("counts, length", [((9, 9, 6, 6), 6), ((9, 9, 9, 6), 9), ((5, 9), 5), ((9, 4, 9), 4),
                                            ((9,) * 7 + (3,), 9), ((9, 9, 9, 9, 3, 3, 3, 3), 9)])
def test_the_sequence_is_as_long_as_enough_cameras_to_track_reach(tmp_path, counts, length):
    """Enough cameras to track a frame: half of them, at least 3, at most all (min_readable_cameras)."""
    names = [f"c{i}" for i in range(len(counts))]
    for i, (name, n) in enumerate(zip(names, counts)):
        add_png(tmp_path, name, frames(n, i))
    with pytest.warns(DataWarning, match=f"the sequence has {length} frames"):
        seq = SequenceFolder(tmp_path, rig(names))
    assert seq.num_frames == length


def test_min_readable_cameras():
    expected = {1: 1, 2: 2, 3: 3, 4: 3, 5: 3, 6: 3, 7: 4, 8: 4, 9: 5, 12: 6}
    assert {c: min_readable_cameras(c) for c in expected} == expected


def test_a_camera_that_ends_early_is_left_out_of_the_frames_it_lacks(tmp_path):
    """The sequence is as long as half the cameras reach; the short camera's missing frames are invalid (NaN), the
    others' are read; a camera longer than that has its last frames unused."""
    data = {"a": frames(9, 1), "b": frames(9, 2), "short": frames(6, 3), "long": frames(12, 4)}
    for name, f in data.items():
        add_png(tmp_path, name, f)
    with pytest.warns(DataWarning, match=r"the sequence has 9 frames; 'short' has 6 \(left out of frames 6-8\), "
                                         r"'long' has 12 \(its last 3 unused\)"):
        seq = SequenceFolder(tmp_path, rig(list(data)))
    assert seq.num_frames == 9
    batches = list(seq.iter_batches(4))
    valid = torch.cat([b.valid for b in batches])  # (9, 4)
    images = torch.cat([b.images for b in batches])
    assert valid[:, [0, 1, 3]].all() and valid[:, 2].tolist() == [True] * 6 + [False] * 3
    assert torch.isnan(images[6:, 2]).all()
    for c, name in enumerate(data):
        n = 6 if name == "short" else 9
        torch.testing.assert_close(images[:n, c], as_images(data[name][:n]), rtol=0, atol=0)


def test_corrupt_frame_gives_invalid_mask_and_nan(two_cams):
    root, data = two_cams
    (root / "frames" / "cam_b" / "000004.png").write_bytes(b"broken")
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    with pytest.warns(DataWarning, match="000004.png"):
        batch = next(seq.iter_batches(10))
    assert batch.valid[:, 1].tolist() == [True] * 4 + [False] + [True] * 5
    assert bool(batch.valid[:, 0].all())
    assert bool(torch.isnan(batch.images[4, 1]).all())
    assert bool(torch.isfinite(batch.images[:, 0]).all()) and bool(torch.isfinite(batch.images[5:, 1]).all())


def test_unreadable_video_fails_at_open(tmp_path):
    (tmp_path / "video").mkdir()
    (tmp_path / "video" / "cam.mp4").write_bytes(b"\x00" * 1000)
    with pytest.raises(InputError, match="cam.mp4"):
        SequenceFolder(tmp_path, rig(["cam"]))


# ------------------------------------------------------------------------------------------------ background


def test_background_frames(two_cams, device):
    root, _ = two_cams
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    assert not seq.has_background and seq.background_frames(5) is None
    bg = {"cam_a": frames(6, 11), "cam_b": frames(6, 12)}
    for name, d in bg.items():
        add_png(root, name, d, folder="background")
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    out = seq.background_frames(3, device=device)  # evenly spaced: frames 0, 2, 5 (linspace 0, 2.5, 5 rounded)
    assert out.shape == (3, 2, 3, H, W) and out.device.type == device.type
    torch.testing.assert_close(out[:, 1].cpu(), as_images(bg["cam_b"][[0, 2, 5]]), **exact_on(device))
    assert seq.background_frames(100).shape[0] == 6


def test_sample_frames_spread_over_a_range_as_float16(two_cams, device, monkeypatch):
    """Frames 1..9 sampled 4 times: linspace(0, 8, 4) = 0, 2.67, 5.33, 8 rounds to 0, 3, 5, 8, offset by the start;
    the pixels are the PNGs' own (float16 keeps 1/255 steps), decoded in blocks of 3 here."""
    import torchtrack.io.sequence as sequence

    monkeypatch.setattr(sequence, "SAMPLE_CHUNK", 3)
    root, data = two_cams
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    idx, out = seq.sample_frames(4, start=1, device=device)
    assert idx == [1, 4, 6, 9]
    assert out.shape == (4, 2, 3, H, W) and out.dtype == torch.float16 and out.device.type == device.type
    for c, name in enumerate(["cam_a", "cam_b"]):
        torch.testing.assert_close(out[:, c].float().cpu(), as_images(data[name][idx]), rtol=0, atol=2e-3)
    assert seq.sample_frames(50, 2, 5)[0] == [2, 3, 4]
    with pytest.raises(InputError, match=r"no frames in \[5, 5\)"):
        seq.sample_frames(3, 5, 5)
    with pytest.raises(InputError, match="max_frames must be >= 1"):
        seq.sample_frames(0)


def test_read_frames_are_the_pngs_of_those_frames(two_cams, device):
    """Frames 1, 4 and 9 in one batch: the PNGs' own pixels (the reference conversion); bad index lists named."""
    root, data = two_cams
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    batch = seq.read_frames([1, 4, 9], device=device)
    assert batch.frame_index.tolist() == [1, 4, 9] and bool(batch.valid.all()) and batch.valid.shape == (3, 2)
    assert batch.images.shape == (3, 2, 3, H, W) and batch.images.device.type == device.type
    for c, name in enumerate(["cam_a", "cam_b"]):
        torch.testing.assert_close(batch.images[:, c].cpu(), as_images(data[name][[1, 4, 9]]), **exact_on(device))
    for bad, match in (([4, 1], "sorted, distinct"), ([2, 2], "sorted, distinct"), ([], "sorted, distinct"),
                       ([3, 10], r"outside \[0, 10\)"), ([-1, 3], "outside")):
        with pytest.raises(InputError, match=match):
            seq.read_frames(bad)


def test_partial_background_is_ignored_with_warning(two_cams):
    root, _ = two_cams
    add_png(root, "cam_a", frames(4, 11), folder="background")
    with pytest.warns(DataWarning, match=r"'cam_b'.*ignoring"):
        seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    assert seq.background_frames(2) is None


# ------------------------------------------------------------------------------------------------ meta, npz


def test_meta_toml(two_cams):
    root, _ = two_cams
    (root / "meta.toml").unlink()
    with pytest.warns(DataWarning, match="assuming"):
        seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    assert seq.fps == DEFAULT_FPS and seq.meta == SequenceMeta()
    (root / "meta.toml").write_text('fps = 24\nsubject_height_m = 1.82\nnotes = "synthetic"\nrenderer = "v1"\n')
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    assert seq.fps == 24.0 and seq.sources[0].fps == 24.0
    assert seq.meta == SequenceMeta(fps=24.0, subject_height_m=1.82, notes="synthetic", extra={"renderer": "v1"})
    (root / "meta.toml").write_text("subject_height = 1.7\n")
    assert read_meta(root / "meta.toml").subject_height_m == 1.7


@pytest.mark.parametrize("text,match", [("fps = -3\n", "'fps' must be a positive"),
                                        ("fps = [\n", "not valid TOML"),
                                        ('subject_height_m = "tall"\n', "subject_height_m"),
                                        ("subject_height_m = 1.7\nsubject_height = 1.7\n", "not both")])
def test_bad_meta(tmp_path, text, match):
    (tmp_path / "meta.toml").write_text(text)
    with pytest.raises(InputError, match=match) as e:
        read_meta(tmp_path / "meta.toml")
    assert "meta.toml" in str(e.value)


def test_meta_fps_overrides_video_with_warning(tmp_path):
    write_video(tmp_path / "video" / "c.mp4", frames(3, 1), fps=25.0)
    (tmp_path / "meta.toml").write_text("fps = 30\n")
    with pytest.warns(DataWarning, match="differs"):
        seq = SequenceFolder(tmp_path, rig(["c"]))
    assert seq.fps == 30.0


def test_gt_and_markers_npz(two_cams):
    root, _ = two_cams
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    assert seq.gt_path is None and seq.load_gt() is None and seq.load_markers2d() is None
    joints = np.random.default_rng(0).normal(size=(10, 16, 3)).astype(np.float32)
    np.savez(root / "gt.npz", fps=np.float64(30), joints3d=joints, joint_names=np.array(["pelvis"] * 16))
    (root / "markers2d.npz").write_bytes(b"not a zip")
    seq = SequenceFolder(root, rig(["cam_a", "cam_b"]))
    gt = seq.load_gt()
    np.testing.assert_array_equal(gt["joints3d"], joints)
    assert gt["joint_names"][0] == "pelvis"
    with pytest.raises(InputError, match="markers2d.npz"):
        seq.load_markers2d()


# ------------------------------------------------------------------------------------------------ real data


def _pose2sim_folder(tmp_path: Path) -> Path:
    videos = shared_data("pose2sim_demo", "videos")
    (tmp_path / "video").mkdir()
    for i in range(1, 5):
        os.symlink(videos / f"cam0{i}.mp4", tmp_path / "video" / f"cam0{i}.mp4")
    shutil.copy(shared_data("pose2sim_demo", "calibration", "Calib_qualisys_pose2sim.toml"),
                tmp_path / "calibration.toml")
    return tmp_path


def _check_pose2sim(seq: SequenceFolder, record) -> None:
    assert seq.camera_names == ["cam_01", "cam_02", "cam_03", "cam_04"]
    assert [s.path.name for s in seq.sources] == [f"cam0{i}.mp4" for i in range(1, 5)]
    assert (seq.num_frames, seq.fps) == (100, 60.0)
    padding = [str(r.message) for r in record if "edge replication" in str(r.message)]
    assert len(padding) == 2 and "'cam_01'" in padding[0] and "'cam_02'" in padding[1]
    assert all("decoded 1080x1920, calibrated 1088x1920" in m for m in padding)
    frame = seq.read_frame(99)  # (4, 3, 1920, 1088)
    assert frame.shape == (4, 3, 1920, 1088) and bool(torch.isfinite(frame).all())
    torch.testing.assert_close(frame[:2, :, :, 1080:], frame[:2, :, :, 1079:1080].expand(2, 3, 1920, 8))
    batch = next(seq.iter_batches(2, start=50, size_wh=(272, 480)))
    assert batch.images.shape == (2, 4, 3, 480, 272) and bool(batch.valid.all())


def test_pose2sim_demo_with_stand_in_rig(tmp_path):
    root = _pose2sim_folder(tmp_path)
    calib = tomllib.loads((root / "calibration.toml").read_text())
    names = [v["name"] for k, v in calib.items() if k != "metadata"]
    stand_in = rig(names, [[int(v) for v in calib[n]["size"]] for n in names])
    with pytest.warns(DataWarning) as record:
        seq = SequenceFolder(root, stand_in)
    _check_pose2sim(seq, record)


def test_pose2sim_demo_with_load_calibration(tmp_path):
    root = _pose2sim_folder(tmp_path)
    try:
        from torchtrack.cameras import load_calibration  # noqa: F401
    except ImportError as e:
        pytest.skip(f"torchtrack.cameras.load_calibration not importable yet: {e}")
    with pytest.warns(DataWarning) as record:
        seq = SequenceFolder(root)
    assert seq.rig.num_cameras == 4 and list(seq.rig.names) == seq.camera_names
    _check_pose2sim(seq, record)
