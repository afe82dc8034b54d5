"""Photometric augmentation: pixel values change, where things are does not,
and the draws are what the module says (shared exposure, grey pairs, a
batch the same whenever it is served)."""

import numpy as np
import pytest

from cpl_keras.training.augment import GREY_PROBABILITY, photometric


def _square_pair(n, size=32):
    """n pairs: a bright square on a dark ground, at a different place in each pair."""
    rng = np.random.default_rng(5)
    left = np.full((n, size, size, 3), 20, np.uint8)
    corners = rng.integers(4, size - 12, (n, 2))
    for image, (row, col) in zip(left, corners):
        image[row:row + 8, col:col + 8] = (230, 200, 180)
    return left, left.copy(), corners + 3.5  # (the squares' centres)


def _centroid(image):
    """Centre of the bright pixels (above the middle of the image's range)."""
    grey = image.astype(np.float64).mean(axis=-1)
    low, high = np.percentile(grey, 5), np.percentile(grey, 95)
    rows, cols = np.nonzero(grey > (low + high) / 2)
    return np.array([rows.mean(), cols.mean()])


def test_pixels_change_but_nothing_moves():
    left, right, centres = _square_pair(60)
    new_left, new_right = photometric(left, right, np.random.default_rng(0))
    assert new_left.shape == left.shape and new_left.dtype == np.uint8
    assert not np.array_equal(new_left, left) and not np.array_equal(new_left, new_right)
    for image, centre in zip(np.concatenate([new_left, new_right]), np.tile(centres, (2, 1))):
        assert np.abs(_centroid(image) - centre).max() < 0.5
    # the inputs are left as they were
    assert np.array_equal(left, _square_pair(60)[0])


def test_the_draws_are_the_generators():
    left, right, _ = _square_pair(8)
    a = photometric(left, right, np.random.default_rng(3))
    b = photometric(left, right, np.random.default_rng(3))
    c = photometric(left, right, np.random.default_rng(4))
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[0], c[0])


def test_exposure_is_shared_by_the_pair_and_grey_pairs_are_grey_on_both_sides():
    rng = np.random.default_rng(1)
    n = 400
    left = rng.integers(40, 216, (n, 8, 8, 3), dtype=np.uint8)
    new_left, new_right = photometric(left, left.copy(), np.random.default_rng(2))
    # one camera: the two images' brightness follows the pair's exposure
    means = new_left.reshape(n, -1).mean(axis=1), new_right.reshape(n, -1).mean(axis=1)
    assert np.corrcoef(*means)[0, 1] > 0.9
    assert np.std(means[0]) > 10  # and the exposure does vary from pair to pair

    def grey(images):  # (JPEG may leave the channels a level or two apart)
        spread = images.astype(int).max(axis=-1) - images.astype(int).min(axis=-1)
        return spread.reshape(len(images), -1).max(axis=1) <= 3

    assert np.array_equal(grey(new_left), grey(new_right))
    assert abs(grey(new_left).mean() - GREY_PROBABILITY) < 0.05
    assert not grey(left).any()


def test_bad_batches_are_refused():
    left = np.zeros((2, 8, 8, 3), np.uint8)
    with pytest.raises(ValueError, match="alike"):
        photometric(left, left[:1], np.random.default_rng(0))


def test_the_sequence_augments_training_batches_reproducibly(tmp_path):
    from cpl_keras.datasets import targets_from_labels
    from cpl_keras.training.sequence import StereoSequence
    from helpers import fixture_labels, write_stereo_fixture

    path = write_stereo_fixture(tmp_path / "d.h5", n=12, image_size=(16, 24))
    targets = targets_from_labels(fixture_labels(12, 24))
    plain = StereoSequence(path, np.arange(12), targets, batch_size=4, shuffle=True, seed=3)
    augmented = StereoSequence(path, np.arange(12), targets, batch_size=4, shuffle=True, seed=3,
                               augment="photometric")
    (x_plain, y_plain), (x_aug, y_aug) = plain[1], augmented[1]
    assert not np.array_equal(x_plain["left_image"], x_aug["left_image"])
    assert all(np.array_equal(y_plain[k], y_aug[k]) for k in y_plain)  # labels exact
    again, _ = augmented[1]
    assert np.array_equal(again["left_image"], x_aug["left_image"])  # the same batch
    augmented.set_epoch(1)
    assert not np.array_equal(augmented[1][0]["left_image"], x_aug["left_image"])
    with pytest.raises(ValueError, match="augment must be"):
        StereoSequence(path, np.arange(12), targets, augment="geometric")
    plain.close()
    augmented.close()
