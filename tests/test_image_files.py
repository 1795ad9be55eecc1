"""Image files as cameras and tools write them: palettes, colour, alpha, TIFF codecs."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest
import tifffile

from plenocl.io.files import read_alpha, read_image

RAW = (np.arange(12 * 10, dtype=np.uint16).reshape(12, 10) * 517) % 65535


def test_lzw_and_deflate_tiffs_read_as_written(tmp_path):
    for codec in ("lzw", "zlib"):
        tifffile.imwrite(tmp_path / f"{codec}.tif", RAW, compression=codec)
        np.testing.assert_array_equal(read_image(tmp_path / f"{codec}.tif"), RAW)


def test_a_grey_palette_is_applied_and_a_colour_one_refused(tmp_path):
    """Palette index 1 stands for grey 136 and index 2 for 232 (the issue's file): the
    image is read as those greys, monotonic in light, not as the indices."""
    greys = np.zeros(256, np.uint16)
    greys[:3] = [0, 136 * 257, 232 * 257]
    index = np.array([[0, 1, 2], [2, 1, 0]], np.uint8)
    tifffile.imwrite(tmp_path / "grey.tif", index, photometric="palette",
                     colormap=np.stack([greys] * 3))
    np.testing.assert_array_equal(read_image(tmp_path / "grey.tif"), greys[index])
    colours = np.stack([greys, greys[::-1], greys])
    tifffile.imwrite(tmp_path / "colour.tif", index, photometric="palette", colormap=colours)
    with pytest.raises(ValueError, match="colour palette"):
        read_image(tmp_path / "colour.tif")


def test_colour_pngs_with_identical_planes_read_as_grey_and_alpha_is_a_mask(tmp_path):
    grey = (RAW // 257).astype(np.uint8)
    alpha = np.full_like(grey, 255)
    alpha[:3] = 0  # rows the renderer did not reach
    iio.imwrite(tmp_path / "rgba.png", np.dstack([grey, grey, grey, alpha]))
    np.testing.assert_array_equal(read_image(tmp_path / "rgba.png"), grey)
    np.testing.assert_array_equal(read_alpha(tmp_path / "rgba.png"), alpha > 0)
    iio.imwrite(tmp_path / "grey.png", grey)
    assert read_alpha(tmp_path / "grey.png") is None


def test_a_colour_image_needs_a_channel(tmp_path):
    rgb = np.dstack([RAW, RAW // 2, RAW // 4]).astype(np.uint16)
    tifffile.imwrite(tmp_path / "rgb.tif", rgb, photometric="rgb")
    with pytest.raises(ValueError, match="--channel"):
        read_image(tmp_path / "rgb.tif")
    np.testing.assert_array_equal(read_image(tmp_path / "rgb.tif", channel="g"), RAW // 2)
    lum = read_image(tmp_path / "rgb.tif", channel="luminance")
    np.testing.assert_allclose(lum, 0.2126 * RAW + 0.7152 * (RAW // 2) + 0.0722 * (RAW // 4),
                               rtol=1e-6)
