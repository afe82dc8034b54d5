"""Image files and arrays: the package's image readers (``read_rgb``,
``read_gray``) and its one resizer (``resize_image``), for calibrate's
pairs and the real-data builders alike. OpenCV is imported on first use."""

from __future__ import annotations

import os

import numpy as np

from cpl_keras.errors import Error


class ImageError(Error):
    """An image file is missing or cannot be read (one-line message)."""


def read_rgb(path, error=ImageError):
    """A uint8 RGB image from ``path``; ``error`` (a one-line ``Error``
    class: the caller's own) when there is no such file or it is not an
    image."""
    import cv2

    if not os.path.isfile(path):
        raise error(f"image not found: {path}")
    image = cv2.imread(os.fspath(path), cv2.IMREAD_COLOR)
    if image is None:
        raise error(f"cannot read {path} as an image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_gray(path, error=ImageError):
    """A uint8 grey image from ``path`` (``read_rgb``'s errors)."""
    import cv2

    if not os.path.isfile(path):
        raise error(f"image not found: {path}")
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
