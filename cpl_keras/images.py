"""Image files and arrays: the package's image readers (``read_rgb``,
``read_gray``) and its one resizer (``resize_image``), for calibrate's
pairs and the real-data builders alike. OpenCV is imported on first use."""

from __future__ import annotations

import os

import numpy as np

from cpl_keras.errors import Error


class ImageError(Error):
    """An image file is missing or cannot be read (one-line message)."""


def check_whole(path, error=ImageError):
    """``error`` unless the image file ``path`` decodes to its end: OpenCV
    fills the missing part of a truncated JPEG or PNG with grey and goes on
    (libjpeg's "Premature end of JPEG file" on stderr the only sign), so
    Pillow decodes it first and says whether it is whole. A format Pillow
    does not know is left to OpenCV."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            image.load()
    except UnidentifiedImageError:
        return
    except (OSError, SyntaxError, ValueError) as reason:
        first = str(reason).strip().splitlines()[0] if str(reason).strip() else "undecodable"
        raise error(f"{path} is truncated or corrupt ({first})") from None


def read_rgb(path, error=ImageError):
    """A uint8 RGB image from ``path``; ``error`` (a one-line ``Error``
    class: the caller's own) when there is no such file, it is not an
    image, or it is truncated (``check_whole``)."""
    import cv2

    if not os.path.isfile(path):
        raise error(f"image not found: {path}")
    check_whole(path, error)
    image = cv2.imread(os.fspath(path), cv2.IMREAD_COLOR)
    if image is None:
        raise error(f"cannot read {path} as an image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_gray(path, error=ImageError):
    """A uint8 grey image from ``path`` (``read_rgb``'s errors)."""
    import cv2

    if not os.path.isfile(path):
        raise error(f"image not found: {path}")
    check_whole(path, error)
    image = cv2.imread(os.fspath(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise error(f"cannot read {path} as an image")
    return image


def resize_image(image, width, height):
    """Resize with area averaging when shrinking, bilinear when enlarging."""
    import cv2

    shrink = width <= image.shape[1] and height <= image.shape[0]
    interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(image), (int(width), int(height)),
                      interpolation=interpolation)
