"""RunLogger: what is written to the TensorBoard event file reads back with TensorBoard's EventAccumulator."""

from __future__ import annotations

import io
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchtrack.checks import InputError, ShapeError
from torchtrack.logging import VIRIDIS_RGB, RunLogger, apply_colour_map, subsample_indices, tile_images


def read_events(log_dir):
    """EventAccumulator over ``log_dir`` keeping every scalar, image and tensor event."""
    from tensorboard.backend.event_processing import event_accumulator as ea

    acc = ea.EventAccumulator(str(log_dir), size_guidance={ea.SCALARS: 0, ea.IMAGES: 0, ea.TENSORS: 0})
    acc.Reload()
    return acc


def decode_png(event) -> np.ndarray:
    """An ImageEvent's PNG -> (H, W, 3) uint8."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(event.encoded_image_string)).convert("RGB"))


def expected_u8(x: torch.Tensor) -> np.ndarray:
    """Plain reference of the uint8 conversion: clamp to [0, 1], NaN -> 0, round(255 x)."""
    x = torch.nan_to_num(x.float().cpu(), nan=0.0).clamp(0, 1)
    return np.floor(x.numpy() * 255 + 0.5).astype(np.uint8)


def test_import_does_not_import_tensorboard():
    code = ("import sys, torchtrack.logging; "
            "print(any(m.split('.')[0] in ('tensorboard', 'tensorflow') or m == 'torch.utils.tensorboard' "
            "for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_scalars_round_trip(tmp_path):
    with RunLogger(tmp_path) as run:
        for step in range(3):
            run.scalars(step, em__iterations=10 + step, ik_residual_m=torch.tensor([0.5 * step]))
    acc = read_events(tmp_path)
    assert sorted(acc.Tags()["scalars"]) == ["em/iterations", "ik_residual_m"]
    em = acc.Scalars("em/iterations")
    assert [e.step for e in em] == [0, 1, 2]
    assert [e.value for e in em] == [10.0, 11.0, 12.0]
    assert [e.value for e in acc.Scalars("ik_residual_m")] == pytest.approx([0.0, 0.5, 1.0])


def test_occupancy_cloud_subsampled_with_colours(tmp_path, device):
    from tensorboard.plugins.mesh import metadata
    from tensorboard.util import tensor_util

    gen = torch.Generator().manual_seed(0)
    centres = (torch.rand(1000, 3, generator=gen) * 2 - 1).to(device)
    colours = torch.rand(1000, 3, generator=gen).to(device)
    with RunLogger(tmp_path) as run:
        run.occupancy_cloud(7, "occupancy/hull", centres, colours, max_points=300)
        run.occupancy_cloud(8, "occupancy/bayes", centres[:50], None, max_points=300)
    acc = read_events(tmp_path)
    assert sorted(acc.Tags()["tensors"]) == ["occupancy/bayes_VERTEX", "occupancy/hull_COLOR",
                                             "occupancy/hull_VERTEX"]
    keep = subsample_indices(1000, 300)
    vert_event = acc.Tensors("occupancy/hull_VERTEX")[0]
    assert vert_event.step == 7
    vertices = tensor_util.make_ndarray(vert_event.tensor_proto)
    assert vertices.shape == (1, 300, 3)
    np.testing.assert_array_equal(vertices[0], centres.cpu()[keep].numpy())
    rgb = tensor_util.make_ndarray(acc.Tensors("occupancy/hull_COLOR")[0].tensor_proto)
    np.testing.assert_array_equal(rgb[0], expected_u8(colours[keep.to(device)]).astype(np.float32))
    meta = acc.SummaryMetadata("occupancy/hull_COLOR")
    assert meta.plugin_data.plugin_name == metadata.PLUGIN_NAME
    parsed = metadata.parse_plugin_metadata(meta.plugin_data.content)
    assert parsed.name == "occupancy/hull" and list(parsed.shape) == [1, 300, 3]
    small = tensor_util.make_ndarray(acc.Tensors("occupancy/bayes_VERTEX")[0].tensor_proto)
    np.testing.assert_array_equal(small[0], centres[:50].cpu().numpy())  # below max_points: all of them


def test_camera_images_one_per_camera(tmp_path, device):
    gen = torch.Generator().manual_seed(1)
    images = torch.rand(3, 3, 12, 20, generator=gen) * 1.2 - 0.1  # some values outside [0, 1]: clamped
    images[1, :, 0, 0] = float("nan")  # an unreadable pixel: black
    names = ["cam0", "cam1", "cam2"]
    with RunLogger(tmp_path) as run:
        run.camera_images(4, "frames", images.to(device), names)
    acc = read_events(tmp_path)
    assert sorted(acc.Tags()["images"]) == ["frames/cam0", "frames/cam1", "frames/cam2"]
    for c, name in enumerate(names):
        event = acc.Images(f"frames/{name}")[0]
        assert (event.step, event.height, event.width) == (4, 12, 20)
        np.testing.assert_array_equal(decode_png(event), expected_u8(images[c]).transpose(1, 2, 0))
    assert (decode_png(acc.Images("frames/cam1")[0])[0, 0] == 0).all()


def test_camera_images_grid(tmp_path):
    images = torch.rand(5, 3, 6, 4, generator=torch.Generator().manual_seed(2))
    with RunLogger(tmp_path) as run:
        run.camera_images(0, "frames", images, [f"c{i}" for i in range(5)], grid=True)
    event = read_events(tmp_path).Images("frames")[0]
    assert (event.height, event.width) == (2 * 6, 3 * 4)  # ceil(sqrt(5)) = 3 columns, 2 rows
    picture = decode_png(event)
    for c in range(5):
        r, k = divmod(c, 3)
        np.testing.assert_array_equal(picture[6 * r:6 * r + 6, 4 * k:4 * k + 4],
                                      expected_u8(images[c]).transpose(1, 2, 0))
    assert (picture[6:, 8:] == 0).all()  # the missing sixth tile is black


def test_probability_images_colour_mapped(tmp_path):
    prob = torch.zeros(2, 4, 5)
    prob[0, 0, 0], prob[0, 0, 1], prob[0, 0, 2] = 0.0, 1.0, float("nan")
    prob[1] = torch.linspace(0, 1, 20).reshape(4, 5)
    with RunLogger(tmp_path) as run:
        run.probability_images(9, "foreground_probability", prob, ["left", "right"])
    acc = read_events(tmp_path)
    left = decode_png(acc.Images("foreground_probability/left")[0])
    right = decode_png(acc.Images("foreground_probability/right")[0])
    assert left.shape == right.shape == (4, 5, 3)
    np.testing.assert_array_equal(left[0, 0], expected_u8(torch.tensor(VIRIDIS_RGB[0])))
    np.testing.assert_array_equal(left[0, 1], expected_u8(torch.tensor(VIRIDIS_RGB[-1])))
    np.testing.assert_array_equal(left[0, 2], [128, 128, 128])  # NaN: grey
    np.testing.assert_array_equal(right, expected_u8(apply_colour_map(prob[1])))


def test_apply_colour_map_matches_interpolation_reference():
    x = torch.tensor([[-0.5, 0.0, 0.1, 0.25, 0.3, 0.5, 0.77, 1.0, 1.5]], dtype=torch.float64)
    out = apply_colour_map(x)
    assert out.shape == (1, 9, 3) and out.dtype == torch.float64
    anchors = np.asarray(VIRIDIS_RGB)
    stops = np.linspace(0, 1, len(anchors))
    ref = np.stack([np.interp(x.numpy().ravel(), stops, anchors[:, ch]) for ch in range(3)], -1)
    np.testing.assert_allclose(out[0].numpy(), ref, atol=1e-12)


def test_subsample_indices():
    np.testing.assert_array_equal(subsample_indices(5, 10).numpy(), np.arange(5))
    idx = subsample_indices(1001, 300)
    assert idx.shape == (300,) and idx[0] == 0 and idx[-1] <= 1000
    assert bool((idx[1:] > idx[:-1]).all())
    assert torch.equal(idx, subsample_indices(1001, 300))  # deterministic
    assert subsample_indices(0, 10).numel() == 0
    with pytest.raises(InputError):
        subsample_indices(10, 0)


def test_tile_images_matches_loop():
    images = torch.arange(7 * 3 * 2 * 3, dtype=torch.float32).reshape(7, 3, 2, 3)
    out = tile_images(images, columns=3)
    ref = torch.zeros(3, 3 * 2, 3 * 3)
    for c in range(7):
        r, k = divmod(c, 3)
        ref[:, 2 * r:2 * r + 2, 3 * k:3 * k + 3] = images[c]
    assert torch.equal(out, ref)


def test_bad_input(tmp_path):
    with RunLogger(tmp_path) as run:
        with pytest.raises(ShapeError, match="centres"):
            run.occupancy_cloud(0, "occ", torch.zeros(10, 2))
        with pytest.raises(ShapeError, match="colours"):
            run.occupancy_cloud(0, "occ", torch.zeros(10, 3), torch.zeros(9, 3))
        with pytest.raises(InputError, match="centres"):
            run.occupancy_cloud(0, "occ", torch.full((2, 3), float("nan")))
        with pytest.raises(ShapeError, match="images"):
            run.camera_images(0, "frames", torch.zeros(2, 3, 4, 4), ["only_one"])
        with pytest.raises(ShapeError, match="prob"):
            run.probability_images(0, "prob", torch.zeros(2, 3, 4, 4), ["a", "b"])
        with pytest.raises(InputError, match="names"):
            run.camera_images(0, "frames", torch.zeros(2, 3, 4, 4), ["a", "a"])
        with pytest.raises(InputError, match="step"):
            run.scalars(-1, loss=1.0)
        with pytest.raises(InputError, match="step"):
            run.scalars(1.5, loss=1.0)
        with pytest.raises(InputError, match="loss"):
            run.scalars(0, loss=torch.zeros(2))
        run.scalars(np.int64(2), loss=1.0)  # numpy integers are fine
    assert [e.step for e in read_events(tmp_path).Scalars("loss")] == [2]
