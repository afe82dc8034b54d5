"""Image files and arrays: the package's image readers (``read_rgb``,
``read_gray``) and its one resizer (``resize_image``), for calibrate's
pairs and the real-data builders alike. OpenCV is imported on first use."""

from __future__ import annotations

import contextlib
import os
import warnings

import numpy as np

from cpl_keras.errors import Error


class ImageError(Error):
    """An image file is missing or cannot be read (one-line message)."""


#: The largest image read, in pixels (width x height): 250 Mpx, above the
#: 200 Mpx photos of today's phone cameras (about 750 MB as RGB). A larger
#: file is refused in one line; Pillow's own bomb check (a warning from
#: about 89 Mpx, an error from about 179 Mpx) is replaced by this limit.
MAX_PIXELS = 250_000_000


@contextlib.contextmanager
def pillow_limit():
    """Pillow opens images up to ``MAX_PIXELS`` without its decompression-bomb
    warning or error (its limit is restored after)."""
    from PIL import Image

    before = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = MAX_PIXELS
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            yield Image
    finally:
        Image.MAX_IMAGE_PIXELS = before


def check_whole(path, error=ImageError):
    """``error`` unless the image file ``path`` decodes to its end: OpenCV
    fills the missing part of a truncated JPEG or PNG with grey and goes on
    (libjpeg's "Premature end of JPEG file" on stderr the only sign), so
    Pillow decodes it first and says whether it is whole. An image of more
    than ``MAX_PIXELS`` is refused before it is decoded. A format Pillow
    does not know is left to OpenCV."""
    from PIL import UnidentifiedImageError

    with pillow_limit() as Image:
        try:
            with Image.open(path) as image:
                width, height = image.size
                if width * height > MAX_PIXELS:
                    raise error(f"{path} is {width}x{height} ({width * height / 1e6:.0f} Mpx), "
                                f"above the {MAX_PIXELS / 1e6:.0f} Mpx this reads; scale it "
                                f"down first")
                image.load()
        except UnidentifiedImageError:
            return
        except Image.DecompressionBombError as reason:  # (a size Pillow finds only later)
            raise error(f"{path} is above the {MAX_PIXELS / 1e6:.0f} Mpx this reads "
                        f"({reason}); scale it down first") from None
        except (OSError, SyntaxError, ValueError) as reason:
            if isinstance(reason, error):
                raise
            first = str(reason).strip().splitlines()[0] if str(reason).strip() else "undecodable"
            raise error(f"{path} is truncated or corrupt ({first})") from None


def _check_path(path, error):
    """``error`` unless ``path`` names an existing file (an array or another
    object is named by its type and shape, never by its repr)."""
    if not isinstance(path, (str, os.PathLike)):
        shape = getattr(path, "shape", None)
        raise error(f"an image file's path is needed, got a {type(path).__name__}"
                    + (f" of shape {tuple(shape)}" if shape is not None else "")
                    + " (write the image to a file first)")
    if not os.path.isfile(path):
        raise error(f"image not found: {path}")


def read_rgb(path, error=ImageError):
    """A uint8 RGB image from ``path``; ``error`` (a one-line ``Error``
    class: the caller's own) when there is no such file, it is not an
    image, or it is truncated (``check_whole``)."""
    import cv2

    _check_path(path, error)
    check_whole(path, error)
    image = cv2.imread(os.fspath(path), cv2.IMREAD_COLOR)
    if image is None:
        raise error(f"cannot read {path} as an image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_gray(path, error=ImageError):
    """A uint8 grey image from ``path`` (``read_rgb``'s errors)."""
    import cv2

    _check_path(path, error)
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
