"""Image files and arrays: the package's image readers (``read_rgb``,
``read_gray``) and its one resizer (``resize_image``), for calibrate's
pairs and the real-data builders alike. OpenCV is imported on first use.

The readers give an image as it is meant to be seen: a file's EXIF
orientation (a phone's portrait or upside-down photo) is applied by Pillow's
``exif_transpose`` whatever OpenCV's version does with it (OpenCV's TIFF
reader failed on orientations 5 to 8); a file without one is decoded by
OpenCV as it always was. OpenCV's own log lines are kept quiet while it
reads: what it could not read is one ``Error`` line instead."""

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


#: EXIF's Orientation tag.
ORIENTATION_TAG = 0x0112
#: What each EXIF orientation says of the stored pixels (1: as stored).
ORIENTATIONS = {1: "upright", 2: "mirrored left-right", 3: "turned 180 degrees",
                4: "mirrored top-bottom", 5: "transposed", 6: "turned 90 degrees clockwise",
                7: "transversed", 8: "turned 90 degrees anticlockwise"}
#: Pillow's modes of 8-bit samples, which ``_upright`` turns.
EIGHT_BIT_MODES = ("1", "L", "LA", "P", "PA", "RGB", "RGBA", "RGBX", "CMYK", "YCbCr")


def check_whole(path, error=ImageError):
    """``error`` unless the image file ``path`` decodes to its end: OpenCV
    fills the missing part of a truncated JPEG or PNG with grey and goes on
    (libjpeg's "Premature end of JPEG file" on stderr the only sign), so
    Pillow decodes it first and says whether it is whole. An image of more
    than ``MAX_PIXELS`` is refused before it is decoded. A format Pillow
    does not know is left to OpenCV. Returns the file's EXIF orientation
    (1 when it has none, or Pillow cannot read it)."""
    from PIL import UnidentifiedImageError

    with pillow_limit() as Image:
        try:
            with Image.open(path) as image:
                width, height = image.size
                if width * height > MAX_PIXELS:
                    raise error(f"{path} is {width}x{height} ({width * height / 1e6:.0f} Mpx), "
                                f"above the {MAX_PIXELS / 1e6:.0f} Mpx this reads; scale it "
                                f"down first")
                # (before ``load``: Pillow's TIFF reader turns the image as it
                # loads and drops the tag)
                orientation = image.getexif().get(ORIENTATION_TAG, 1)
                image.load()
        except UnidentifiedImageError:
            return 1
        except Image.DecompressionBombError as reason:  # (a size Pillow finds only later)
            raise error(f"{path} is above the {MAX_PIXELS / 1e6:.0f} Mpx this reads "
                        f"({reason}); scale it down first") from None
        except (OSError, SyntaxError, ValueError) as reason:
            if isinstance(reason, error):
                raise
            first = str(reason).strip().splitlines()[0] if str(reason).strip() else "undecodable"
            raise error(f"{path} is truncated or corrupt ({first})") from None
    return orientation if orientation in ORIENTATIONS else 1


def exif_orientation(path):
    """The EXIF orientation of the image file ``path`` (1 when it has none,
    or it cannot be read): ``ORIENTATIONS`` says what each means."""
    try:
        with pillow_limit() as Image, Image.open(path) as image:
            orientation = image.getexif().get(ORIENTATION_TAG, 1)
    except Exception:  # (not an image Pillow knows: the readers say so)
        return 1
    return orientation if orientation in ORIENTATIONS else 1


@contextlib.contextmanager
def _opencv_quiet():
    """OpenCV's log lines ("[ WARN:0@0.1] global grfmt_tiff.cpp ...") off
    while it reads: what it could not read is the reader's one line."""
    import cv2

    logging = cv2.utils.logging
    before = logging.setLogLevel(logging.LOG_LEVEL_SILENT)
    try:
        yield cv2
    finally:
        logging.setLogLevel(before)


def _upright(path, orientation, error):
    """The uint8 RGB image of ``path`` turned as its EXIF ``orientation``
    says (Pillow's ``exif_transpose``)."""
    from PIL import ImageOps

    with pillow_limit() as Image, Image.open(path) as image:
        if image.mode not in EIGHT_BIT_MODES:
            raise error(f"{path} is a {image.mode} image {ORIENTATIONS[orientation]} by its "
                        f"EXIF orientation ({orientation}), which this cannot turn; save it "
                        "upright with 8 bits per channel first")
        image.load()  # (a TIFF is turned here, its tag dropped: no second turn below)
        return np.asarray(ImageOps.exif_transpose(image).convert("RGB"))


def _decode(path, flags, error):
    """``cv2.imread(path, flags)`` without OpenCV's log lines; ``error`` when
    it cannot read the file, naming floating-point samples (a float TIFF)."""
    with _opencv_quiet() as cv2:
        image = cv2.imread(os.fspath(path), flags)
        if image is not None:
            return image
        raw = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    if raw is not None and raw.dtype.kind == "f":
        raise error(f"{path} has floating-point samples ({raw.dtype}); this reads images of "
                    "8 or 16 bits per channel: convert it first")
    raise error(f"cannot read {path} as an image")


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
    """A uint8 RGB image from ``path``, upright as its EXIF orientation says;
    ``error`` (a one-line ``Error`` class: the caller's own) when there is no
    such file, it is not an image, or it is truncated (``check_whole``)."""
    import cv2

    _check_path(path, error)
    orientation = check_whole(path, error)
    if orientation != 1:
        return _upright(path, orientation, error)
    return cv2.cvtColor(_decode(path, cv2.IMREAD_COLOR, error), cv2.COLOR_BGR2RGB)


def read_gray(path, error=ImageError):
    """A uint8 grey image from ``path`` (``read_rgb``'s orientation and errors)."""
    import cv2

    _check_path(path, error)
    orientation = check_whole(path, error)
    if orientation != 1:
        return cv2.cvtColor(_upright(path, orientation, error), cv2.COLOR_RGB2GRAY)
    return _decode(path, cv2.IMREAD_GRAYSCALE, error)


def resize_image(image, width, height):
    """Resize with area averaging when shrinking, bilinear when enlarging."""
    import cv2

    shrink = width <= image.shape[1] and height <= image.shape[0]
    interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(image), (int(width), int(height)),
                      interpolation=interpolation)
