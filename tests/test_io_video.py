"""Video and image-folder writers and sources: round trips, damaged files, real videos."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from conftest import shared_data
from torchtrack.checks import InputError, ShapeError
from torchtrack.io.video import (DataWarning, ImageFolderSource, VideoFileSource, open_video_source, write_frames_png,
                                 write_video)


def smooth_frames(n: int = 12, h: int = 120, w: int = 160) -> list[np.ndarray]:
    """Gradients with a moving disc: content a lossy codec can keep (~32 dB with mp4v at this size)."""
    yy, xx = np.mgrid[0:h, 0:w]
    frames = []
    for i in range(n):
        f = np.stack([xx * 200 // w + 2 * i, yy * 200 // h, np.full_like(xx, 90)], -1).astype(np.uint8)
        cv2.circle(f, (w // 6 + 4 * i, h // 2), h // 6, (240, 40, 30), -1)
        frames.append(f)
    return frames


def random_frames(n: int = 7, h: int = 24, w: int = 32, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, h, w, 3), dtype=np.uint8)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0 ** 2 / mse))


def no_temporaries(folder) -> bool:
    return not any(p.startswith(".") for p in os.listdir(folder))


# ------------------------------------------------------------------------------------------------ image folders


def test_png_round_trip_exact(tmp_path):
    frames = random_frames()
    assert write_frames_png(tmp_path / "f", frames) == len(frames)
    assert sorted(os.listdir(tmp_path / "f")) == [f"{i:06d}.png" for i in range(len(frames))]
    src = open_video_source(tmp_path / "f", fps=25.0)
    assert isinstance(src, ImageFolderSource)
    assert (src.num_frames, src.size_wh, src.fps, len(src)) == (7, (32, 24), 25.0, 7)
    out, valid = src.read()
    assert out.dtype == np.uint8 and out.shape == frames.shape and valid.all()
    np.testing.assert_array_equal(out, frames)  # RGB in, RGB out: no channel swap anywhere
    np.testing.assert_array_equal(src.read(2, 5)[0], frames[2:5])
    np.testing.assert_array_equal(src.read_indices([1, 4, 6])[0], frames[[1, 4, 6]])
    np.testing.assert_array_equal(src.read_frame(3), frames[3])
    # the channel order on disk is OpenCV's BGR: a pure red frame is red when read by cv2 as BGR
    assert tuple(cv2.imread(str(tmp_path / "f" / "000000.png"))[0, 0]) == tuple(frames[0, 0, 0, ::-1])


def test_png_folder_replaced_atomically(tmp_path):
    write_frames_png(tmp_path / "f", random_frames(5))
    write_frames_png(tmp_path / "f", random_frames(2, seed=1))
    assert sorted(os.listdir(tmp_path / "f")) == ["000000.png", "000001.png"]

    def failing():
        yield from random_frames(2, seed=2)
        raise RuntimeError("renderer crashed")

    with pytest.raises(RuntimeError):
        write_frames_png(tmp_path / "f", failing())
    np.testing.assert_array_equal(open_video_source(tmp_path / "f").read()[0], random_frames(2, seed=1))
    assert no_temporaries(tmp_path)


def test_image_folder_natural_order_and_jpg(tmp_path):
    frames = random_frames(3, seed=3)
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i, name in enumerate(["f2.png", "f10.jpg", "f1.PNG"]):
        cv2.imwrite(str(folder / name), cv2.cvtColor(frames[i], cv2.COLOR_RGB2BGR))
    (folder / "notes.txt").write_text("not a frame")
    src = ImageFolderSource(folder)
    assert [p.name for p in src.files] == ["f1.PNG", "f2.png", "f10.jpg"]
    out, _ = src.read()
    np.testing.assert_array_equal(out[0], frames[2])
    np.testing.assert_array_equal(out[1], frames[0])
    assert psnr(out[2], frames[1]) > 10  # jpeg, lossy on noise


def test_image_folder_corrupt_frame(tmp_path):
    frames = random_frames(4)
    write_frames_png(tmp_path / "f", frames)
    (tmp_path / "f" / "000002.png").write_bytes(b"not a png")
    src = open_video_source(tmp_path / "f")
    with pytest.raises(InputError, match=r"frame 2 .*000002\.png"):
        src.read()
    with pytest.warns(DataWarning, match="000002.png"):
        out, valid = src.read(strict=False)
    assert valid.tolist() == [True, True, False, True]
    assert (out[2] == 0).all()
    np.testing.assert_array_equal(out[3], frames[3])


def test_image_folder_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="not found"):
        ImageFolderSource(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no png"):
        ImageFolderSource(tmp_path / "empty")
    write_frames_png(tmp_path / "f", random_frames(2))
    (tmp_path / "f" / "000000.png").write_bytes(b"garbage")
    with pytest.raises(InputError, match="000000.png"):
        ImageFolderSource(tmp_path / "f")
    write_frames_png(tmp_path / "g", random_frames(2))
    cv2.imwrite(str(tmp_path / "g" / "000002.png"), np.zeros((5, 5, 3), np.uint8))
    with pytest.raises(InputError, match="000002.png.*5x5"):
        ImageFolderSource(tmp_path / "g").read()


# ------------------------------------------------------------------------------------------------ video files


def test_mp4_round_trip_psnr(tmp_path):
    frames = smooth_frames()
    path = tmp_path / "cam.mp4"
    assert write_video(path, frames, fps=25.0) == len(frames)
    assert no_temporaries(tmp_path)
    src = open_video_source(path)
    assert isinstance(src, VideoFileSource)
    assert (src.num_frames, src.size_wh, src.fps) == (12, (160, 120), 25.0)
    assert VideoFileSource(path, verify_frame_count=True).num_frames == 12
    out, valid = src.read()
    assert valid.all()
    assert min(psnr(a, b) for a, b in zip(out, frames)) > 30
    # the red disc stays red: RGB order survives the BGR codec edge
    assert out[0, 60, 160 // 6, 0] > 200 and out[0, 60, 160 // 6, 2] < 80


def test_video_sequential_access(tmp_path):
    frames = smooth_frames(10)
    write_video(tmp_path / "v.mp4", frames, fps=10)
    src = open_video_source(tmp_path / "v.mp4")
    full, _ = src.read()
    # forward jumps, then a step back (re-open), give the same decoded frames as one pass
    np.testing.assert_array_equal(src.read(6, 8)[0], full[6:8])
    np.testing.assert_array_equal(src.read(2, 4)[0], full[2:4])
    np.testing.assert_array_equal(src.read_indices([0, 5, 9])[0], full[[0, 5, 9]])
    np.testing.assert_array_equal(src.read_frame(9), full[9])
    with pytest.raises(InputError, match="outside"):
        src.read(5, 11)
    with pytest.raises(InputError, match="increasing"):
        src.read_indices([3, 2])
    src.close()
    np.testing.assert_array_equal(src.read(0, 1)[0], full[:1])


def test_write_video_atomic_on_failure(tmp_path):
    path = tmp_path / "v.mp4"
    write_video(path, smooth_frames(3), fps=10)
    before = path.read_bytes()

    def failing():
        yield from smooth_frames(2)
        raise RuntimeError("renderer crashed")

    with pytest.raises(RuntimeError, match="renderer crashed"):
        write_video(path, failing(), fps=10)
    assert path.read_bytes() == before and no_temporaries(tmp_path)


def test_write_video_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="no frames"):
        write_video(tmp_path / "a.mp4", [], fps=10)
    with pytest.raises(InputError, match="even"):
        write_video(tmp_path / "a.mp4", [np.zeros((11, 16, 3), np.uint8)], fps=10)
    with pytest.raises(ShapeError, match="frame 1"):
        write_video(tmp_path / "a.mp4", [np.zeros((16, 16, 3), np.uint8), np.zeros((16, 18, 3), np.uint8)], fps=10)
    with pytest.raises(ShapeError, match="uint8"):
        write_video(tmp_path / "a.mp4", [np.zeros((16, 16, 3), np.float32)], fps=10)
    with pytest.raises(InputError, match="fps"):
        write_video(tmp_path / "a.mp4", [np.zeros((16, 16, 3), np.uint8)], fps=0)
    with pytest.raises(RuntimeError, match="codecs"):
        write_video(tmp_path / "a.mp4", [np.zeros((16, 16, 3), np.uint8)], fps=10, fourccs=["QQQQ"])
    assert not (tmp_path / "a.mp4").exists() and no_temporaries(tmp_path)


def test_garbage_and_missing_video(tmp_path):
    bad = tmp_path / "garbage.mp4"
    bad.write_bytes(b"this is not a video" * 100)
    with pytest.raises(InputError, match="garbage.mp4"):
        open_video_source(bad)
    with pytest.raises(InputError, match="not found.*nothing.mp4"):
        open_video_source(tmp_path / "nothing.mp4")


def test_truncated_mp4_is_an_error_at_open(tmp_path):
    """OpenCV writes the index (moov) at the end of an mp4: cut in half, the file cannot be opened at all."""
    path = tmp_path / "cut.mp4"
    write_video(path, smooth_frames(12), fps=10)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="cut.mp4"):
        open_video_source(path)


def test_damaged_mp4_partial_read_with_valid_mask(tmp_path):
    """Zeroed bytes in the middle of the stream: index intact, some frames undecodable."""
    frames = smooth_frames(20)
    path = tmp_path / "damaged.mp4"
    write_video(path, frames, fps=10)
    data = bytearray(path.read_bytes())
    moov = data.find(b"moov")
    mid = moov // 2
    data[mid:mid + 400] = bytes(400)
    path.write_bytes(bytes(data))
    try:
        src = open_video_source(path)
    except InputError as e:  # a clear error is an acceptable outcome of damage too
        assert "damaged.mp4" in str(e)
        return
    assert src.num_frames == 20  # the container's count
    with pytest.warns(DataWarning, match=r"damaged.mp4: some frames could not be decoded"):
        out, valid = src.read(strict=False)
    assert out.shape == (20, 120, 160, 3)
    assert 0 < valid.sum() < 20, "the zeroed bytes should make some (not all) frames undecodable"
    assert (out[~valid] == 0).all()
    assert valid[:3].all() and min(psnr(out[i], frames[i]) for i in range(3)) > 30  # before the damage
    first_bad = int(np.argmin(valid))
    # frames after the damage sit at their own index (placed by timestamp, not by decode count: FFmpeg drops
    # the damaged pictures, and counting would shift every later frame by the number dropped)
    later = [i for i in range(first_bad + 4, 20) if valid[i]]
    assert later
    for i in later:
        own = psnr(out[i], frames[i])
        assert own > 30 and own > psnr(out[i], frames[i - 1]) and (i == 19 or own > psnr(out[i], frames[i + 1]))
    with pytest.raises(InputError, match=rf"damaged.mp4: frame {first_bad} could not be decoded"):
        open_video_source(path).read()
    # a verifying count decodes the file: the last decodable frame sets the count
    last_valid = int(np.nonzero(valid)[0][-1])
    assert VideoFileSource(path, verify_frame_count=True).num_frames == last_valid + 1


# ------------------------------------------------------------------------------------------------ real videos


@pytest.mark.parametrize("cam,width", [("cam01", 1080), ("cam03", 1088)])
def test_pose2sim_videos(cam, width):
    src = open_video_source(shared_data("pose2sim_demo", "videos", f"{cam}.mp4"))
    assert (src.num_frames, src.size_wh, src.fps) == (100, (width, 1920), 60.0)
    out, valid = src.read(98, 100)
    assert out.shape == (2, 1920, width, 3) and valid.all()
    assert 20 < out.mean() < 235  # a real picture, not a blank frame
