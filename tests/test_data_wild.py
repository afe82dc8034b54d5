"""The wild protocol: the cameras protocol's geometry and labels under a
randomised appearance (sun, haze, white balance) per configuration."""

import h5py
import numpy as np
import pytest

from cpl_keras.data import protocols, scenes
from cpl_keras.data.generate import generate_dataset
from cpl_keras.data.pair import pair_setup, render_pair
from cpl_keras.data.storage import StereoFile


def _read(path):
    with h5py.File(path, "r") as f:
        return (f["left"][()], f["right"][()],
                {k: f["labels"][k][()] for k in f["labels"]})


@pytest.fixture(scope="module")
def wild_and_cameras(tmp_path_factory):
    """12 pairs (2 configurations) at 32 px of wild and of cameras, seed 5."""
    root = tmp_path_factory.mktemp("wild")
    kwargs = dict(pairs=12, seed=5, image_size=32, workers=1, progress=False)
    return {p: generate_dataset(root / f"{p}.h5", protocol=p, **kwargs)
            for p in ("wild", "cameras")}


def test_wild_has_the_cameras_labels_and_other_images(wild_and_cameras):
    left_w, right_w, labels_w = _read(wild_and_cameras["wild"])
    left_c, right_c, labels_c = _read(wild_and_cameras["cameras"])
    assert labels_w.keys() == labels_c.keys()
    for name in labels_w:
        if name != "disparity_released":       # StereoBM's, computed from the images
            assert labels_w[name].tobytes() == labels_c[name].tobytes(), name
    for wild, cameras in ((left_w, left_c), (right_w, right_c)):
        assert wild.shape == cameras.shape and wild.dtype == np.uint8
        # every pair looks different (its configuration's sun, haze, white balance)
        assert all(not np.array_equal(w, c) for w, c in zip(wild, cameras))


def test_wild_configurations_are_the_cameras_ones_with_an_appearance(wild_and_cameras):
    with StereoFile(wild_and_cameras["wild"]) as data:
        meta = data.metadata
    cameras = protocols.configurations("cameras", 5, 12, 32)
    assert meta["protocol"] == "wild" and len(meta["configurations"]) == 2
    for wild, cam in zip(meta["configurations"], cameras):
        assert {k: v for k, v in wild.items() if k != "appearance"} == cam
    ranges = meta["ranges"]["appearance"]
    assert ranges == {**{k: list(v) for k, v in protocols.WILD_APPEARANCE.items()},
                      "haze_m_drawn": "log-uniform"}
    looks = [c["appearance"] for c in meta["configurations"]]
    for look in looks:
        sun = np.array(look["sun"])
        assert np.linalg.norm(sun) == pytest.approx(1.0)
        elevation = np.degrees(np.arcsin(sun[2]))
        assert elevation == pytest.approx(look["sun_elevation_deg"])
        assert ranges["sun_elevation_deg"][0] <= elevation <= ranges["sun_elevation_deg"][1]
        assert ranges["haze_m"][0] <= look["haze_m"] <= ranges["haze_m"][1]
        cool, warm = (np.array(ranges[k]) for k in ("haze_colour_cool", "haze_colour_warm"))
        np.testing.assert_allclose(look["haze_colour"],
                                   cool + look["haze_blend"] * (warm - cool))
        gains = np.array(look["white_balance"])
        assert gains.shape == (3,)
        t, g = ranges["white_balance_temperature"][1], ranges["white_balance_tint"][1]
        assert gains[0] - 1 == pytest.approx(1 - gains[2]) and abs(gains[0] - 1) <= t
        assert abs(gains[1] - 1) <= g
    assert looks[0] != looks[1]
    for key in ("sun", "haze_m", "haze_colour", "white_balance"):
        assert looks[0][key] != looks[1][key], key


def test_wild_appearance_is_drawn_per_configuration_and_changes_no_town():
    """A configuration's appearance depends on (seed, configuration) only;
    rendering it leaves the cached towns as they were."""
    town = scenes.make_town(0)
    sun, haze, colour = town.sun.copy(), town.haze, town.haze_colour.copy()
    few = protocols.configurations("wild", 1, 16, 16)
    many = protocols.configurations("wild", 1, 400, 16)
    assert few[1]["appearance"] == many[1]["appearance"]
    assert few[1]["appearance"] != protocols.configurations("wild", 2, 16, 16)[1]["appearance"]
    setup = pair_setup("wild", 1, 16, 16, 0)
    assert setup["town"] is not town and setup["town"].buildings is town.buildings
    np.testing.assert_array_equal(setup["town"].sun, few[0]["appearance"]["sun"])
    assert setup["white_balance"] == few[0]["appearance"]["white_balance"]
    render_pair("wild", 1, 16, 16, 0)
    assert scenes.make_town(0) is town and town.haze == haze
    np.testing.assert_array_equal(town.sun, sun)
    np.testing.assert_array_equal(town.haze_colour, colour)
    assert pair_setup("cameras", 1, 16, 16, 0)["white_balance"] is None


def test_zoom_is_wild_with_the_fov_drawn_from_10_to_120_degrees():
    """zoom: wild's rigs and appearance, the horizontal fov from its wider
    range at the same draw (so the fov maps affinely from wild's), fx from
    the fov (Eq. focal_from_fov) and fy keeping the rig's fy / fx."""
    pairs, size = 8 * 300, 112
    wild = protocols.configurations("wild", 3, pairs, size)
    zoom = protocols.configurations("zoom", 3, pairs, size)
    assert len(zoom) == len(wild) == 300
    lo, hi = protocols.ZOOM_FOV_DEG
    assert (lo, hi) == (10.0, 120.0)
    w_lo, w_hi = protocols.CAMERA_RIG_FOV_DEG["wild"]
    changed = {"fov_deg", "fx", "fy"}
    for z, w in zip(zoom, wild):
        assert {k: v for k, v in z.items() if k not in changed} == \
            {k: v for k, v in w.items() if k not in changed}
        # the same uniform draw on the wider interval
        share = (w["fov_deg"] - w_lo) / (w_hi - w_lo)
        assert z["fov_deg"] == pytest.approx(lo + share * (hi - lo))
        assert z["fx"] == pytest.approx(size / 2 / np.tan(np.radians(z["fov_deg"]) / 2))
        assert z["fy"] / z["fx"] == pytest.approx(w["fy"] / w["fx"])
    fov = np.array([z["fov_deg"] for z in zoom])
    assert fov.min() < 15 and fov.max() > 115 and np.mean(fov < 40) > 0.2
    ranges = protocols.ranges("zoom")
    assert ranges["fov_deg"] == [10.0, 120.0] and protocols.ranges("wild")["fov_deg"] == [40.0, 120.0]
