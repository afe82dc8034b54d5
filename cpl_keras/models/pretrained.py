"""Towers that start from ImageNet weights (``ModelOptions.backbone_weights``).

The paper's InceptionV3 towers start from ImageNet weights; this project's
start from random initialisation unless ``backbone_weights`` names a file:

* ``"imagenet"``: Keras's file of InceptionV3's ImageNet weights without
  the classifier (``IMAGENET_FILE``), taken from Keras's cache
  (``$KERAS_HOME/models``, default ``~/.keras/models``) when it is there,
  else downloaded into it from ``IMAGENET_URL`` as keras.applications
  does (checked against Keras's own MD5);
* a path: such a file, in Keras's legacy HDF5 layout (the file
  keras.applications downloads: a group per layer, ``layer_names`` and
  ``weight_names`` attributes) or in Keras 3's ``.weights.h5`` layout
  (``keras.applications.InceptionV3(include_top=False,
  weights=None).save_weights(...)``). The layout is told by the file's
  contents, not its name.

Keras reads either into a stock InceptionV3 tower (``load_into``), before
the faster layers are swapped in (they keep the weights). Layer names do
not identify a layer across networks (Keras numbers them per process:
``conv2d_94`` is the second tower's first convolution), so Keras matches
them by their place in the network: the legacy layout layer by layer in
order, Keras 3's by class and order; every layer's weight count and shapes
are checked. A file that does not fit is refused in one line naming it.

Planning reads a file's checksum (``checksum``) without Keras; only the
download and ``load_into`` import it.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import tempfile
import warnings

from cpl_keras.models.options import OptionsError

#: ``backbone_weights``' name of Keras's ImageNet weights.
IMAGENET = "imagenet"
#: The file keras.applications downloads for InceptionV3(include_top=False).
IMAGENET_FILE = "inception_v3_weights_tf_dim_ordering_tf_kernels_notop.h5"
#: Where keras.applications downloads it from.
IMAGENET_URL = ("https://storage.googleapis.com/tensorflow/keras-applications/inception_v3/"
                + IMAGENET_FILE)
#: keras.applications' own check of that download.
IMAGENET_MD5 = "bcbd6486424b2319ff4ef7d526e38f63"


class WeightsError(OptionsError):
    """A backbone weights file that cannot be used (one line naming it)."""


def keras_home():
    """Keras's folder (``$KERAS_HOME``, else ``~/.keras``; ``/tmp/.keras``
    where the home folder cannot be written, as Keras decides)."""
    home = os.environ.get("KERAS_HOME")
    if home:
        return home
    base = os.path.expanduser("~")
    return os.path.join(base if os.access(base, os.W_OK) else "/tmp", ".keras")


def named(weights):
    """``backbone_weights`` as a run records it: "imagenet", or the file's
    absolute path."""
    if weights == IMAGENET:
        return weights
    return os.path.abspath(os.path.expanduser(weights))


def weights_file(weights):
    """The file ``weights`` ("imagenet" or a path) names, as an absolute
    path: "imagenet" from Keras's cache, downloaded there when missing.
    WeightsError (one line) when it is missing, not HDF5, in neither of
    Keras's layouts, or cannot be downloaded."""
    if weights != IMAGENET:
        path = named(weights)
    else:
        path = os.path.join(keras_home(), "models", IMAGENET_FILE)
        if not os.path.isfile(path):
            path = _download()
    layout(path)
    return path


def _download():
    """Keras's download of ``IMAGENET_FILE`` into its cache (its messages
    held back: a failure is one line)."""
    import keras

    try:
        with contextlib.redirect_stdout(io.StringIO()):
            return os.path.abspath(keras.utils.get_file(
                IMAGENET_FILE, IMAGENET_URL, cache_subdir="models", file_hash=IMAGENET_MD5,
                cache_dir=keras_home()))
    except Exception as error:  # (Keras raises a bare Exception when the fetch fails)
        reason = (str(error).strip().splitlines() or [type(error).__name__])[0]
        reason = reason.rpartition(" -- ")[2] or reason  # (Keras's line repeats the URL)
        raise WeightsError(f"cannot download InceptionV3's ImageNet weights ({reason}): "
                           f"download {IMAGENET_URL} and pass the file with "
                           f"--backbone-weights FILE") from None


def layout(path):
    """"legacy" or "keras3": the layout of the weights file ``path``
    (WeightsError, one line naming it, when it is neither)."""
    if not os.path.exists(path):
        raise WeightsError(f"{path}: no such backbone weights file")
    if not os.path.isfile(path):
        raise WeightsError(f"{path}: not a file (backbone weights)")
    import h5py

    if not h5py.is_hdf5(path):
        raise WeightsError(f"{path}: not an HDF5 file, so not InceptionV3 weights")
    try:
        with h5py.File(path, "r") as f:
            if "layer_names" in f.attrs or (
                    isinstance(f.get("model_weights"), h5py.Group)
                    and "layer_names" in f["model_weights"].attrs):
                return "legacy"
            if isinstance(f.get("layers"), h5py.Group):
                return "keras3"
    except OSError as error:
        raise WeightsError(f"{path}: unreadable HDF5 file ({error})") from None
    raise WeightsError(f"{path}: not a Keras weights file (neither the legacy layout's "
                       f"layer_names nor a Keras 3 .weights.h5 file's layers)")


def checksum(path):
    """The sha256 of the file ``path`` (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def check_checksum(path, expected):
    """WeightsError (one line) unless ``path``'s sha256 is ``expected``."""
    found = checksum(path)
    if found != expected:
        raise WeightsError(f"{path}: sha256 {found} is not the {expected} the run was made "
                           f"with; give that file")


def load_into(tower, path):
    """Read the weights file ``path`` into ``tower``, a stock InceptionV3
    without its classifier; returns its weights (``get_weights()``).
    WeightsError (one line naming the file) when they do not fit."""
    kind = layout(path)
    suffix = ".weights.h5" if kind == "keras3" else ".h5"
    fits = path.endswith(suffix) and not (kind == "legacy" and path.endswith(".weights.h5"))
    with tempfile.TemporaryDirectory() as folder:
        source = path
        if not fits:  # (Keras picks the reader by the name's ending)
            source = os.path.join(folder, "backbone" + suffix)
            os.symlink(path, source)
        try:
            with warnings.catch_warnings():  # (Keras warns for each layer it cannot fill)
                warnings.simplefilter("ignore")
                tower.load_weights(source)
        except (ValueError, KeyError, TypeError, OSError) as error:
            reason = (str(error).strip().splitlines() or [type(error).__name__])[0]
            raise WeightsError(f"{path}: not InceptionV3's weights without its classifier "
                               f"(include_top=False): {reason.rstrip(':')}") from None
    return tower.get_weights()
