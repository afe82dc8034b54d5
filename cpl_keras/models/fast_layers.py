"""The towers' faster layers: ``PatchConv2D`` and ``ViewMaxPooling2D``.

Speed, not arithmetic: each is a Keras layer whose weights, configuration
and outputs are those of ``Conv2D`` and ``MaxPooling2D`` (to float32
round-off; a pooling's gradient differs only where a window's largest
inputs tie), computed another way where XLA:CPU's own kernels are slow for
the shape (docs/performance.md). ``cpl_keras.models.backbones`` swaps them
into the towers (``with_faster_layers``) and Deep-Homo is built with them
(``cpl_keras.models.deep_homo``); ``xla_layers_only`` turns both back into
XLA's computations for a benchmark. On a GPU or TPU both always take the
plain layers' computations (``on_accelerator``), and the towers keep
``Conv2D`` and ``MaxPooling2D``.

Both are registered with Keras as ``cpl_keras>PatchConv2D`` and
``cpl_keras>ViewMaxPooling2D`` (the names saved models carry), so a saved
model loads with ``safe_mode=True`` once this module is imported
(``import cpl_keras.saving`` does it).
"""

from __future__ import annotations

import contextlib
import functools

import keras
from keras import ops


#: PatchConv2D computes the kernel gradient through matrix products on output
#: maps at least this large with at least this many input channels (measured
#: at 112 x 112: faster for InceptionV3's stem, 32-80 channels, and for
#: Deep-Homo's 64-128 channel maps of 28-112 px; slower for InceptionV3's
#: 11 x 11 maps and for small_resnet's 16-channel 28 x 28 maps).
TAP_GRADIENT_MIN_SIDE = 24
TAP_GRADIENT_MIN_CHANNELS = 32


@functools.cache
def on_accelerator():
    """Whether Keras computes on a GPU or TPU (its first device is not a CPU).

    Both layers' other paths exist for XLA:CPU's kernels; on an accelerator
    they take ``Conv2D``'s and ``MaxPooling2D``'s own computations (cuDNN's
    on a GPU), so the towers are built with neither. Measured on one H200
    (JAX 0.11.2, ``bench/bench_train.py``, 2 InceptionV3 towers at 112 px,
    batch 16): with the patch paths the run had not finished 40 timed steps
    after 125 s; with ``--plain-conv`` it compiled and ran its first epoch in
    53 s and trained 369 samples/s (docs/performance.md).
    """
    try:
        devices = keras.distribution.list_devices()
    except (AttributeError, NotImplementedError, RuntimeError, ValueError):
        devices = None  # (Keras 3.15 has no device list under PyTorch)
    # (without one the patch paths are taken: Conv2D's and MaxPooling2D's
    # results on any device)
    return bool(devices) and not str(devices[0]).lower().startswith("cpu")


@keras.saving.register_keras_serializable(package="cpl_keras")
class PatchConv2D(keras.layers.Conv2D):
    """``Conv2D`` computed through matrix products over image patches where
    XLA:CPU's convolution kernels are slow for the shape.

    The layer, its weights and its outputs are those of ``Conv2D`` (to
    float32 round-off). Two shapes take another path (``path``):

    * ``"patches"``: a "same" convolution whose kernel is larger than its
      input in both dimensions (InceptionV3's 3x3 convolutions on 2 x 2
      maps). The input is zero-padded as "same" padding does, the
      kernel_h x kernel_w shifted views are stacked along the channels
      (kernel order: row, column, input channel) and multiplied by the kernel
      reshaped to (kernel_h * kernel_w * in_channels, filters); the gradients
      are those of that product.
    * ``"tap-gradient"``: a stride-1 convolution (odd kernel if "same") with
      an output map of at least ``TAP_GRADIENT_MIN_SIDE`` on both sides and
      at least ``TAP_GRADIENT_MIN_CHANNELS`` input channels (InceptionV3's
      stem, Deep-Homo's larger maps). The forward pass and the input
      gradient are XLA's convolutions (a "valid" one computed as "same" and
      cropped); the kernel gradient, which XLA:CPU computes as one
      convolution with a window the size of the map, is one matrix product
      per kernel row: the padded input's rows for that kernel row,
      transposed, times the output gradient shifted by each kernel column
      (the shifts side by side, made once for all rows). For Deep-Homo's
      conv1_2 that took 250 ms against 361 ms for the input's shifted views
      side by side, 408 ms per tap and 476-844 ms for XLA's kernel
      (``bench/bench_kernel_gradient.py``).

    Anything else (strides, dilation, groups, channels_first, or a kernel
    that fits a small map in either dimension) is plain ``Conv2D``: patches
    were slower for InceptionV3's 1x7 kernels on 5 x 5 maps, and tap
    gradients for its 11 x 11 maps and for small_resnet's 16-channel maps
    (``bench/bench_conv_shapes.py``, ``bench/bench_train.py``).
    """

    def path(self, input_shape):
        """``"patches"``, ``"tap-gradient"`` or ``"conv"`` for inputs of this
        shape (``"conv"`` on an accelerator: ``on_accelerator``)."""
        if on_accelerator():
            return "conv"
        height, width = input_shape[1], input_shape[2]
        kernel_h, kernel_w = self.kernel_size
        if (self.data_format != "channels_last" or tuple(self.strides) != (1, 1)
                or tuple(self.dilation_rate) != (1, 1) or self.groups != 1
                or height is None or width is None or self.kernel_size == (1, 1)):
            return "conv"
        if self.padding == "same" and kernel_h > height and kernel_w > width:
            return "patches"
        out_h, out_w = ((height, width) if self.padding == "same"
                        else (height - kernel_h + 1, width - kernel_w + 1))
        odd = kernel_h % 2 == 1 and kernel_w % 2 == 1
        if (min(out_h, out_w) >= TAP_GRADIENT_MIN_SIDE and (self.padding == "valid" or odd)
                and input_shape[-1] is not None and input_shape[-1] >= TAP_GRADIENT_MIN_CHANNELS):
            return "tap-gradient"
        return "conv"

    def convolution_op(self, inputs, kernel):
        path = self.path(inputs.shape)
        if path == "patches":
            return self._patches(inputs, kernel)
        if path == "tap-gradient":
            return self._tap_gradient(inputs, kernel)
        return super().convolution_op(inputs, kernel)

    def _padded(self, inputs):
        """``inputs`` zero-padded as this layer's "same" padding does (as is for "valid")."""
        if self.padding != "same":
            return inputs
        kernel_h, kernel_w = self.kernel_size
        top, left = (kernel_h - 1) // 2, (kernel_w - 1) // 2
        return ops.pad(inputs, [[0, 0], [top, kernel_h - 1 - top],
                                [left, kernel_w - 1 - left], [0, 0]])

    def _views(self, padded, height, width):
        """The kernel_h x kernel_w shifted (height, width) views of ``padded``, row-major."""
        kernel_h, kernel_w = self.kernel_size
        return [padded[:, i:i + height, j:j + width, :]
                for i in range(kernel_h) for j in range(kernel_w)]

    def _patches(self, inputs, kernel):
        patches = ops.concatenate(
            self._views(self._padded(inputs), inputs.shape[1], inputs.shape[2]), axis=-1)
        return ops.matmul(patches, ops.reshape(kernel, (-1, self.filters)))

    def _tap_gradient(self, inputs, kernel):
        kernel_h, kernel_w = self.kernel_size
        padding = self.padding
        kernel = ops.copy(kernel)  # a tensor, not a variable (torch, tensorflow)

        @ops.custom_gradient
        def convolution(x, k):
            def gradient(*args, upstream=None):
                upstream = args[0] if upstream is None else upstream
                height = upstream.shape[1]
                # one product per kernel row: the padded input's rows for that
                # kernel row (full padded width) ^T @ the output gradient
                # shifted by each kernel column, the kernel_w shifts side by
                # side: dW[i, j] = sum over n, y, x of
                # padded[n, y + i, x + j] * upstream[n, y, x]
                padded = self._padded(x)
                shifted = ops.reshape(ops.concatenate([
                    ops.pad(upstream, [[0, 0], [0, 0], [j, kernel_w - 1 - j], [0, 0]])
                    for j in range(kernel_w)], axis=-1), (-1, kernel_w * self.filters))
                kernel_gradient = ops.stack([
                    ops.transpose(ops.reshape(ops.matmul(
                        ops.transpose(ops.reshape(padded[:, i:i + height], (-1, x.shape[-1]))),
                        shifted), (x.shape[-1], kernel_w, self.filters)), (1, 0, 2))
                    for i in range(kernel_h)])
                # the input gradient: a correlation with the flipped kernel, in and out swapped
                flipped = ops.transpose(ops.flip(ops.flip(k, 0), 1), (0, 1, 3, 2))
                if padding == "valid":
                    upstream = ops.pad(upstream, [[0, 0], [kernel_h - 1, kernel_h - 1],
                                                  [kernel_w - 1, kernel_w - 1], [0, 0]])
                input_gradient = ops.conv(upstream, flipped, strides=1,
                                          padding="same" if padding == "same" else "valid")
                return input_gradient, kernel_gradient

            if padding == "same":
                return ops.conv(x, k, strides=1, padding="same"), gradient
            # "valid" as "same" cropped: XLA:CPU's valid 3x3 kernel on the stem's
            # 55 x 55 x 32 maps took 4-5x as long as its same kernel
            top, left = (kernel_h - 1) // 2, (kernel_w - 1) // 2
            out_h, out_w = x.shape[1] - kernel_h + 1, x.shape[2] - kernel_w + 1
            same = ops.conv(x, k, strides=1, padding="same")
            return same[:, top:top + out_h, left:left + out_w, :], gradient

        return convolution(inputs, kernel)


@keras.saving.register_keras_serializable(package="cpl_keras")
class ViewMaxPooling2D(keras.layers.MaxPooling2D):
    """``MaxPooling2D`` computed as the element-wise maximum of the windows'
    strided views where that is faster.

    ``path`` is ``"views"`` for "valid" padding, channels last and a known
    map size: the output is the maximum of the pool_h x pool_w views
    ``inputs[:, i::stride_h, j::stride_w]`` (each cut to the output's size),
    reduced pairwise, and its gradient is that of the maximum, element-wise,
    instead of XLA's select-and-scatter. The forward values are
    ``MaxPooling2D``'s exactly; the gradient differs only where a window's
    largest inputs tie (the maximum splits the window's gradient evenly
    between them, XLA's pooling gives it all to one). Forward and gradient
    together, jitted: Deep-Homo's first 2x2 pooling (16 x 112 x 112 x 64)
    18 ms against 151 ms; InceptionV3's first 3x3, stride-2 pooling (16 x 53
    x 53 x 64) 3.3 ms against 34 ms (paper_results/notes/deep-homo-speed.md).
    Other padding is
    ``MaxPooling2D`` as is (``"pool"``).
    """

    def path(self, input_shape):
        """``"views"`` or ``"pool"`` for inputs of this shape (``"pool"`` on
        an accelerator: ``on_accelerator``)."""
        if on_accelerator():
            return "pool"
        views = self.padding == "valid" and self.data_format == "channels_last"
        return "views" if views and None not in input_shape[1:3] else "pool"

    def call(self, inputs):
        if self.path(inputs.shape) == "pool":
            return super().call(inputs)
        (pool_h, pool_w), (stride_h, stride_w) = self.pool_size, self.strides
        rows = (inputs.shape[1] - pool_h) // stride_h * stride_h + 1
        columns = (inputs.shape[2] - pool_w) // stride_w * stride_w + 1
        views = [inputs[:, i:i + rows:stride_h, j:j + columns:stride_w]
                 for i in range(pool_h) for j in range(pool_w)]
        while len(views) > 1:  # pairwise: a tree of depth log2(pool_h * pool_w)
            views = [ops.maximum(views[k], views[k + 1]) if k + 1 < len(views) else views[k]
                     for k in range(0, len(views), 2)]
        return views[0]


@contextlib.contextmanager
def xla_layers_only():
    """Within the block, ``PatchConv2D`` and ``ViewMaxPooling2D`` layers take
    ``Conv2D``'s and ``MaxPooling2D``'s own computations (XLA's kernels), so a
    benchmark can time the same network both ways. The path is chosen when a
    step is traced: trace (compile) the model inside the block."""
    conv_path, pool_path = PatchConv2D.path, ViewMaxPooling2D.path
    PatchConv2D.path = lambda layer, shape: "conv"
    ViewMaxPooling2D.path = lambda layer, shape: "pool"
    try:
        yield
    finally:
        PatchConv2D.path, ViewMaxPooling2D.path = conv_path, pool_path
