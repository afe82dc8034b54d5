"""Photographic surface textures for the synthetic towns.

The photographs ship with scikit-image (``skimage.data``: brick, grass,
gravel, moon, camera), so nothing is downloaded. Each grey photo is
mirror-tiled (seamless), normalised, tinted into an RGB *material* and stored
as a small mip pyramid: level ``l`` is the texture blurred by a Gaussian of
``2**l / 2`` texels, all levels at the same resolution, so a lookup is one
integer gather ``bank.pixels[material, level, row, col]``. The renderer picks
the level from the pixel footprint, which keeps distant road and walls from
turning into sampling noise.

This module is numpy/scipy only (no deep-learning backend).
"""

from __future__ import annotations

import functools

import numpy as np

#: Texture side in texels (a power of two, so wrapping is a bit mask).
SIZE = 256
#: Number of mip levels.
LEVELS = 5

# name: (photo, mean RGB, contrast)
MATERIALS = {
    "asphalt": ("gravel", (0.27, 0.27, 0.28), 0.55),
    "asphalt_light": ("gravel", (0.36, 0.35, 0.34), 0.5),
    "sidewalk": ("brick", (0.62, 0.60, 0.56), 0.45),
    "paving": ("gravel", (0.58, 0.55, 0.50), 0.5),
    "curb": ("gravel", (0.70, 0.70, 0.68), 0.3),
    "grass": ("grass", (0.30, 0.45, 0.18), 0.9),
    "brick_red": ("brick", (0.55, 0.30, 0.22), 0.8),
    "brick_yellow": ("brick", (0.68, 0.58, 0.40), 0.7),
    "plaster": ("moon", (0.80, 0.78, 0.72), 0.6),
    "concrete": ("gravel", (0.60, 0.60, 0.58), 0.35),
    "stone": ("camera", (0.62, 0.60, 0.57), 0.35),
    "bark": ("grass", (0.30, 0.22, 0.15), 0.8),
    "foliage": ("grass", (0.20, 0.36, 0.14), 1.2),
    "paint": ("gravel", (0.80, 0.80, 0.80), 0.08),
    "metal": ("gravel", (0.45, 0.46, 0.48), 0.15),
    "clouds": (None, (1.0, 1.0, 1.0), 1.0),
}
MATERIAL_NAMES = tuple(MATERIALS)
MATERIAL_ID = {name: i for i, name in enumerate(MATERIAL_NAMES)}


def _photo(name):
    import skimage.data

    image = getattr(skimage.data, name)().astype(np.float32) / 255.0
    if image.ndim == 3:
        image = image[..., :3].mean(axis=-1)
    # Central crop, halve it (512 -> 256 texels), mirror-tile to SIZE.
    h, w = image.shape
    image = image[(h - 512) // 2:(h - 512) // 2 + 512, (w - 512) // 2:(w - 512) // 2 + 512]
    image = image.reshape(256, 2, 256, 2).mean(axis=(1, 3))
    half = image[: SIZE // 2, : SIZE // 2]
    top = np.concatenate([half, half[:, ::-1]], axis=1)
    return np.concatenate([top, top[::-1]], axis=0)


def _clouds(seed=7):
    """Soft procedural cloud cover (periodic), values in [0, 1]."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    field = np.zeros((SIZE, SIZE), np.float32)
    for sigma, weight in ((24, 1.0), (10, 0.5), (4, 0.25)):
        noise = rng.standard_normal((SIZE, SIZE)).astype(np.float32)
        layer = ndimage.gaussian_filter(noise, sigma, mode="wrap")
        field += weight * layer / layer.std()
    field = (field - field.mean()) / field.std()
    return np.clip((field - 0.3) * 0.8, 0.0, 1.0)


def _pyramid(gray):
    from scipy import ndimage

    levels = [gray]
    for level in range(1, LEVELS):
        levels.append(ndimage.gaussian_filter(gray, 2.0 ** level / 2.0, mode="wrap"))
    return np.stack(levels)


class TextureBank:
    """All materials as one uint8 array ``pixels[material, level, row, col, rgb]``."""

    def __init__(self):
        # Tinting is linear in the grey photo, so each photo's mip pyramid is
        # computed once and tinted per material.
        pyramids = {}
        stacks = []
        for name in MATERIAL_NAMES:
            photo, mean, contrast = MATERIALS[name]
            if photo is None:
                if "clouds" not in pyramids:
                    pyramids["clouds"] = _pyramid(_clouds())
                rgb = pyramids["clouds"][..., None] * np.ones(3, np.float32)
            else:
                if photo not in pyramids:
                    p = _photo(photo)
                    pyramids[photo] = _pyramid((p - p.mean()) / (p.std() + 1e-6))
                gray = pyramids[photo]
                rgb = np.asarray(mean, np.float32) * (1.0 + 0.25 * contrast * gray[..., None])
            stacks.append(np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8))
        self.pixels = np.stack(stacks)            # (M, L, S, S, 3)
        rgba = np.concatenate([self.pixels, np.zeros(self.pixels.shape[:-1] + (1,), np.uint8)],
                              axis=-1)
        # one uint32 per texel: a lookup is a single 1-D gather
        self.packed = np.ascontiguousarray(rgba).view(np.uint32).reshape(-1)
        self.mask = SIZE - 1

    def lookup(self, material, s, t, footprint):
        """RGB in [0, 1] (float32, (n, 3)) of ``material`` at texel coords (s, t).

        ``material`` is an int or an int array; ``footprint`` is the size of
        one image pixel in texels, which selects the mip level (log2 of it).
        """
        level = np.clip(np.log2(np.maximum(footprint, 1.0)), 0, LEVELS - 1).astype(np.intp)
        col = s.astype(np.intp) & self.mask          # truncation: at most one texel off below 0
        row = t.astype(np.intp) & self.mask
        index = ((np.asarray(material, np.intp) * LEVELS + level) * SIZE + row) * SIZE + col
        texels = self.packed[index].view(np.uint8).reshape(-1, 4)[:, :3]
        return texels.astype(np.float32) * np.float32(1.0 / 255.0)


@functools.lru_cache(maxsize=1)
def texture_bank():
    """The process-wide texture bank (built once per process, about 0.5 s)."""
    return TextureBank()
