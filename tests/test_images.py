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


#: What each EXIF orientation asks of the stored pixels, by hand.
UPRIGHT = {1: lambda a: a, 2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1],
           4: lambda a: a[::-1], 5: lambda a: a.swapaxes(0, 1),
           6: lambda a: np.rot90(a, -1), 7: lambda a: np.rot90(a, 2).swapaxes(0, 1),
           8: lambda a: np.rot90(a, 1)}


@pytest.mark.parametrize("suffix", ["png", "tiff", "webp", "jpg"])
def test_every_exif_orientation_is_applied_in_every_format(tmp_path, suffix):
    """A file's EXIF orientation turns the image as every viewer shows it,
    in both readers and whatever OpenCV does with it (its TIFF reader could
    not read orientations 5 to 8: "cannot read ... as an image", and an
    OpenCV log line)."""
    import cv2
    from PIL import Image

    stored = np.zeros((16, 24, 3), np.uint8)
    stored[:8, :8] = 255                             # corner blocks mark the turn
    stored[8:, 16:] = 120                            # (grey: no chroma for JPEG to blur)
    options = {"webp": {"lossless": True}, "jpg": {"quality": 95}}.get(suffix, {})
    seen = None
    for orientation, turn in UPRIGHT.items():
        exif = Image.Exif()
        exif[images.ORIENTATION_TAG] = orientation
        path = tmp_path / f"o{orientation}.{suffix}"
        Image.fromarray(stored).save(path, exif=exif.tobytes(), **options)
        rgb, grey = images.read_rgb(path), images.read_gray(path)
        if seen is None:                             # (orientation 1: as stored)
            seen = rgb
            assert suffix == "jpg" or np.array_equal(seen, stored)
        want = turn(seen)                            # (a JPEG as its decoder sees it)
        assert rgb.shape == want.shape and grey.shape == want.shape[:2], orientation
        assert np.abs(rgb.astype(int) - want).max() <= 2, orientation
        want_grey = cv2.cvtColor(np.ascontiguousarray(want), cv2.COLOR_RGB2GRAY)
        assert np.abs(grey.astype(int) - want_grey).max() <= 4, orientation


def test_a_float_tiff_is_one_line_naming_its_samples_and_no_opencv_log(tmp_path, capfd):
    """A TIFF of 32-bit float samples: one line that says so (OpenCV printed
    "[ WARN:0@0.1] global grfmt_tiff.cpp:811 readData OpenCV TIFF: ... can
    not handle images with 32-bit samples", and the reader said only
    "cannot read ... as an image")."""
    import cv2

    for name, image in (("rgb.tiff", np.random.default_rng(0).random((8, 10, 3))),
                        ("grey.tiff", np.random.default_rng(1).random((8, 10)))):
        cv2.imwrite(str(tmp_path / name), image.astype(np.float32))
        for read in (images.read_rgb, images.read_gray):
            with pytest.raises(images.ImageError) as error:
                read(tmp_path / name)
            assert str(error.value) == (f"{tmp_path / name} has floating-point samples "
                                        "(float32); this reads images of 8 or 16 bits per "
                                        "channel: convert it first")
    assert capfd.readouterr() == ("", "")
