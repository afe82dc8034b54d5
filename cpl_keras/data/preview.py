"""The generator's preview (``--preview``): a PNG contact sheet of a few
pairs, left | right, each with its labels, rendered like the dataset's
(``pair.render_pair``); no dataset file is read or written."""

from __future__ import annotations

import math

from cpl_keras import camera
from cpl_keras.cli import make_parent
from cpl_keras.data.generate import check_arguments, check_output_path
from cpl_keras.data.pair import render_pair
from cpl_keras.files import atomic_path


def preview_indices(protocol, pairs, count=8):
    """``count`` pair indices spread over the dataset (and so over configurations)."""
    count = min(count, pairs)
    return sorted({int(round(i * (pairs - 1) / max(count - 1, 1))) for i in range(count)})


def write_preview(path, protocol, pairs, seed=0, image_size=112, count=8, columns=2):
    """A PNG contact sheet of ``count`` pairs (left | right) with their labels.

    The projection pixel (u, v) is marked in the right image and the point
    (u + d, v) in the left image (where it would be for a rectified rig).
    """
    from PIL import Image, ImageDraw

    pairs, seed, image_size, _ = check_arguments(protocol, pairs, seed, image_size, None)
    path = check_output_path(path)
    indices = preview_indices(protocol, pairs, count)
    W = image_size
    text_h = 36
    cell_w, cell_h = 2 * W + 6, W + text_h
    rows = math.ceil(len(indices) / columns)
    sheet = Image.new("RGB", (columns * cell_w + (columns - 1) * 8, rows * cell_h), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for n, i in enumerate(indices):
        left, right, lab = render_pair(protocol, seed, pairs, image_size, i)
        x0 = (n % columns) * (cell_w + 8)
        y0 = (n // columns) * cell_h
        sheet.paste(Image.fromarray(left), (x0, y0))
        sheet.paste(Image.fromarray(right), (x0 + W + 6, y0))
        u, v = lab["u"], lab["v"]
        draw.rectangle([x0 + W + 6 + u - 2, y0 + v - 2, x0 + W + 6 + u + 2, y0 + v + 2],
                       outline=(255, 0, 255))
        fov = math.degrees(camera.fov_from_focal(lab["fx"], W))
        lines = [
            f"#{i} cfg {lab['config_id']} town {lab['town_id'] + 1} frame {lab['frame_index']}",
            f"fov {fov:.0f} b {lab['baseline']:.2f} pitch {math.degrees(lab['pitch']):.1f}d",
            f"d {lab['disparity']:.2f}px X {lab['X']:.1f} Y {lab['Y']:.1f} Z {lab['Z']:.1f}",
        ]
        for k, line in enumerate(lines):
            draw.text((x0 + 1, y0 + W + 1 + 11 * k), line, fill=(0, 0, 0))

    make_parent(path)
    with atomic_path(path) as tmp:
        sheet.save(tmp, optimize=True)
    return path
