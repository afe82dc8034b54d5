"""``cpl_keras/images.py``: the image readers' limits and refusals."""

import warnings

import numpy as np
import pytest

from cpl_keras import images


def _png(path, size=20):
    import cv2

    cv2.imwrite(str(path), np.full((size, size, 3), 128, np.uint8))
    return path


def test_an_image_above_the_pixel_limit_is_refused_in_one_line(tmp_path, monkeypatch):
    path = _png(tmp_path / "big.png")
    monkeypatch.setattr(images, "MAX_PIXELS", 300)
    with pytest.raises(images.ImageError, match=r"big.png is 20x20 \(0 Mpx\), above the 0 Mpx "
                       r"this reads; scale it down first") as error:
        images.read_rgb(path)
    assert "\n" not in str(error.value)


def test_an_image_within_the_limit_reads_without_pillows_bomb_warning(tmp_path, monkeypatch):
    from PIL import Image

    path = _png(tmp_path / "large.png")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 100)  # (as if 20x20 were a bomb: 400 px)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (any warning fails the test)
        assert images.read_rgb(path).shape == (20, 20, 3)
    assert Image.MAX_IMAGE_PIXELS == 100  # (Pillow's own limit is left as it was)
    assert images.MAX_PIXELS >= 200_000_000  # (a phone's 200 Mpx photo reads)


def test_an_array_instead_of_a_path_is_named_by_type_and_shape_in_one_line():
    with pytest.raises(images.ImageError, match=r"an image file's path is needed, got a "
                       r"ndarray of shape \(480, 640, 3\)") as error:
        images.read_rgb(np.zeros((480, 640, 3), np.uint8))
    assert "\n" not in str(error.value) and len(str(error.value)) < 200
    with pytest.raises(images.ImageError, match="image not found"):
        images.read_gray("no-such-file.png")
