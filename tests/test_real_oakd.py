"""The OAK-D Lite rig (cpl_keras.real.oakd): measured disparity, exact crop
intrinsics, labels in the project's rig convention."""

import numpy as np
import pytest

from cpl_keras import camera
from cpl_keras.data.storage import StereoFile
from cpl_keras.real import oakd

SIZE = 32


def test_measured_disparity_finds_a_known_shift():
    """A textured left image and the same image shifted 12 px left as the
    right one: the left-right-checked disparity is 12 where it is kept."""
    rng = np.random.default_rng(0)
    texture = (rng.random((120, 200)) * 255).astype(np.uint8)
    texture = np.repeat(np.repeat(texture, 2, 0), 2, 1)          # 240 x 400, blobs of 2 px
    left = np.stack([texture] * 3, -1)
    right = np.zeros_like(left)
    right[:, :-12] = left[:, 12:]                                  # right(u) = left(u + 12)
    d = oakd.measure_disparity(left, right, max_disparity=32)
    kept = np.isfinite(d[:, 40:-40])
    assert kept.mean() > 0.5
    assert np.median(d[:, 40:-40][kept]) == pytest.approx(12.0, abs=0.25)


def test_calibration_and_pairs_of_the_shipped_rig():
    cal = oakd.load_calibration()
    assert (cal["width"], cal["height"]) == (640, 480)
    assert cal["fx"] == pytest.approx(451.03, abs=0.01) and cal["baseline"] == 0.075
    assert len(oakd.find_pairs()) == 12


@pytest.fixture(scope="module")
def oakd_file(tmp_path_factory):
    return oakd.build_oakd(tmp_path_factory.mktemp("oakd") / "oakd.h5", crops=2, image_size=SIZE)


def test_labels_follow_the_crop_and_the_rig_convention(oakd_file):
    cal = oakd.load_calibration()
    with StereoFile(oakd_file) as f:
        lab, meta = f.labels, f.metadata
        left, right = f.read_pairs(np.arange(f.num_pairs))
    assert meta["rig"] == "oakd" and meta["rectified"] and "measured" in meta["disparity"]
    assert left.shape == (24, SIZE, SIZE, 3)
    # exact intrinsics of a crop + resize: focal scaled by output / crop size
    np.testing.assert_allclose(lab["fx"], cal["fx"] * SIZE / lab["crop_width"], rtol=1e-6)
    np.testing.assert_allclose(lab["fy"], cal["fy"] * SIZE / lab["crop_height"], rtol=1e-6)
    # the right image's pixel and its left match differ by the disparity
    np.testing.assert_allclose(lab["u_left"] - lab["u"], lab["disparity"], atol=1e-4)
    assert np.all(lab["disparity"] > 0)
    # a rectified rig: no rotation, the right camera 7.5 cm to the right
    assert np.all(lab["pitch"] == 0) and np.all(lab["ty"] == -0.075)
    # the point projects back to the pixel and disparity (Eqs. 4a-5c)
    u, v, d = camera.world_to_image(lab["X"], lab["Y"], lab["Z"], lab["fx"], lab["fy"],
                                    lab["u0"], lab["v0"], lab["baseline"], lab["pitch"],
                                    lab["tx"], lab["ty"], lab["tz"])
    np.testing.assert_allclose(u, lab["u"], atol=1e-3)
    np.testing.assert_allclose(d, lab["disparity"], rtol=1e-5)
    # indoor depths: 0.4-8 m in front of the camera
    assert np.all((lab["X"] > 0.4) & (lab["X"] < 8.0))
    assert sorted(set(lab["pair_index"].tolist())) == list(range(12))
