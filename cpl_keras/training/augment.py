"""Photometric augmentation: what real cameras do to an image and the renderer does not.

``photometric(left, right, rng)`` returns a new batch of uint8 stereo pairs
(n, H, W, 3) in which each pair has, drawn independently per pair:

* an exposure: a gamma in [0.6, 1.6] and a gain in [0.7, 1.3] shared by the
  two images (one camera model), each image's gain moved by up to 5 % more
  (two sensors are never identical);
* grey images, both of the pair (probability 0.1), as a monochrome rig gives;
* a Gaussian blur, both images alike (probability 0.3, sigma 0.3-1.2 px);
* sensor noise, independent per image (sigma 0-6 grey levels; grey on a
  grey pair);
* JPEG compression, each image on its own (probability 0.3, quality 30-90).

Only the pixels' values change, never where anything is, so every label
(intrinsics, extrinsics, disparity, the projected point) stays exact. It is
off by default (``StereoSequence(augment=None)``; ``train.py --augment``):
the paper trained on CARLA's images as rendered. The draws come from
``rng`` alone, so a batch is augmented the same way whenever it is served
(``StereoSequence`` seeds it from its seed, the epoch and the batch index,
and a resumed run sees the batches an uninterrupted one saw).
"""

from __future__ import annotations

import numpy as np

#: Each effect's probability and range (see the module doc).
GAMMA = (0.6, 1.6)
GAIN = (0.7, 1.3)
GAIN_PER_IMAGE = 0.05
GREY_PROBABILITY = 0.1
BLUR_PROBABILITY, BLUR_SIGMA = 0.3, (0.3, 1.2)
NOISE_SIGMA = (0.0, 6.0)
JPEG_PROBABILITY, JPEG_QUALITY = 0.3, (30, 90)


def photometric(left, right, rng):
    """``(left, right)`` uint8 batches (n, H, W, 3) with each pair's exposure,
    colour, blur, noise and compression redrawn (see the module doc)."""
    left, right = np.asarray(left), np.asarray(right)
    if left.shape != right.shape or left.ndim != 4 or left.shape[-1] != 3:
        raise ValueError(f"photometric: left and right must be (n, H, W, 3) alike, got "
                         f"{left.shape} and {right.shape}")
    out_left, out_right = np.empty_like(left), np.empty_like(right)
    for i in range(len(left)):
        out_left[i], out_right[i] = _pair(left[i], right[i], rng)
    return out_left, out_right


def _pair(left, right, rng):
    gamma, gain = rng.uniform(*GAMMA), rng.uniform(*GAIN)
    grey = rng.random() < GREY_PROBABILITY
    blur = rng.uniform(*BLUR_SIGMA) if rng.random() < BLUR_PROBABILITY else 0.0
    images = []
    for image in (left, right):
        x = image.astype(np.float32) / 255.0
        x = np.power(x, gamma) * gain * (1.0 + rng.uniform(-GAIN_PER_IMAGE, GAIN_PER_IMAGE))
        if grey:
            x = np.repeat(x @ np.float32([0.299, 0.587, 0.114])[:, None], 3, axis=-1)
        x = _blurred(x, blur)
        # (a grey pair's noise is grey too: one value per pixel)
        noise_shape = x.shape[:2] + (1,) if grey else x.shape
        x = x * 255.0 + rng.normal(0.0, rng.uniform(*NOISE_SIGMA), noise_shape)
        x = np.clip(np.rint(x), 0, 255).astype(np.uint8)
        if rng.random() < JPEG_PROBABILITY:
            x = _jpeg(x, int(rng.integers(JPEG_QUALITY[0], JPEG_QUALITY[1] + 1)))
        images.append(x)
    return images


def _blurred(image, sigma):
    if sigma <= 0:
        return image
    import cv2

    return cv2.GaussianBlur(image, (0, 0), sigmaX=float(sigma))


def _jpeg(image, quality):
    """``image`` (RGB uint8) through JPEG at ``quality``."""
    import cv2

    ok, encoded = cv2.imencode(".jpg", image[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # (never for a valid uint8 image; keep it as it was)
        return image
    return cv2.imdecode(encoded, cv2.IMREAD_COLOR)[..., ::-1]
