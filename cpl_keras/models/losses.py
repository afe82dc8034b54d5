"""Training losses: the camera projection loss (CPL) and Deep-Homo's loss.

Camera projection loss, as the paper writes it
----------------------------------------------
For ground truth omega = (fx, fy, u0, v0, b, d, pitch, tx, ty, tz, X, Y, Z) and
a prediction omega', Eq. 6 is the mean of the 13 absolute errors::

    L(omega', omega) = 1/13 * sum_k |omega'_k - omega_k|

where the predicted X, Y, Z come out of the camera equations (Eqs. 4a-5c).
To keep an error in one parameter from being blamed on another, the loss is
disentangled (Eq. 7): ``L_p`` evaluates L with only parameter p predicted
and every other one at its ground truth, so the projected point moves only
because of p::

    L_p = 1/13 * (|p' - p| + |X(p') - X| + |Y(p') - Y| + |Z(p') - Z|)

for the 10 camera parameters, and ``L_X = 1/13 |X' - X|`` (likewise Y, Z)
for the graph's own outputs. The projection pixel (u, v) of the ground truth
is recovered from the ground-truth point by the inverse camera model, so the
dataset needs to supply nothing beyond the 13 targets.

* MTL-CPL-U: ``L* = (L_fx + ... + L_Z) / 13`` (Eq. 7, uniform weights).
* MTL-CPL-A: ``L* = sum_i alpha_i L_i`` with learned alpha_i (Eq. 9). Plain
  learned multipliers can shrink to 0 and switch the loss off (the release's
  gates did). We learn ``alpha_i = exp(-s_i)`` and add ``s_i`` to the loss
  (the log-variance weighting of Kendall et al., 2018): a small alpha_i costs
  a large s_i, so the weights settle at alpha_i ~ 1 / L_i instead of
  collapsing, which is exactly the balancing of heterogeneous ranges the
  paper asks of them. Each s_i starts at log L_i of the first training batch
  (``initial_log_variances``), so the weights start balanced, and is floored
  ``log(ADAPTIVE_WEIGHT_RANGE)`` below that, so a term that reaches 0 cannot
  drive the objective to minus infinity.

Exact disentangling. The terms of the 10 parameters are computed here from
the parameter heads' outputs, so each trains only its own head. The X, Y, Z
terms compare the camera graph's outputs; in the model (as the paper writes
it) the graph sees the parameters through ``stop_gradient``, so those errors
reach only the graph's own free parameters, the pixel heads u, v. With
``disentangle="partial"`` (the first version of this project) they reach
every head the graph reads.

Point errors in metres or relative to depth (not the paper's). Eq. 7 adds
each pair's point error in metres, so a parameter's term weighs a pair by how
far that parameter moves its point: the disparity moves the depth xCam =
fx b / d (Eq. 4a) by fx b / d^2 per pixel and a pitch error moves a point by
its distance times the error, so near pairs weigh least. With
``point_errors="relative"`` each pair's point error (X, Y and Z together) is
divided by its ground-truth depth xCam: the pitch's point error then weighs
every pair alike, and the disparity's goes as 1 / d instead of 1 / d^2. An
ablation that tests that reading of where MTL-CPL-A loses; ``"metres"`` is
Eq. 7 and the default.
"""

from __future__ import annotations

import math

import numpy as np
from keras import ops

from cpl_keras import camera
from cpl_keras.models.variants import POINT_ERRORS


def projection_terms(y_true, y_pred, floors=None, point_errors="metres"):
    """The 13 disentangled projection losses ``L_p`` of Eq. 7, in TARGETS order.

    ``y_true`` and ``y_pred`` map each name of ``camera.TARGETS`` to a
    (batch, 1) tensor; ``floors`` are the camera graph's divisor floors
    (``camera.FLOORS``); ``point_errors``: one of ``POINT_ERRORS`` (the
    module docstring). Returns a list of 13 scalars (batch means).
    """
    if point_errors not in POINT_ERRORS:
        raise ValueError(f"point_errors must be one of {', '.join(POINT_ERRORS)}, "
                         f"got {point_errors!r}")
    tensor = camera.tensor_ops(floors=floors)
    gt = {name: ops.cast(y_true[name], "float32") for name in camera.TARGETS}
    params = {name: gt[name] for name in camera.PARAMETERS}
    # The ground-truth projection pixel, by the inverse of Eqs. 4a-5c.
    u, v, _ = camera.world_to_image(
        gt["X"], gt["Y"], gt["Z"], gt["fx"], gt["fy"], gt["u0"], gt["v0"],
        gt["baseline"], gt["pitch"], gt["tx"], gt["ty"], gt["tz"], ops=tensor,
    )
    # Each pair's point errors are in metres, or in units of its depth.
    depth = None
    if point_errors == "relative":
        depth = camera.depth_from_disparity(gt["fx"], gt["baseline"], gt["disparity"], ops=tensor)
    n = float(len(camera.TARGETS))
    terms = []
    for name in camera.PARAMETERS:
        one_predicted = dict(params, **{name: y_pred[name]})
        X, Y, Z = camera.image_to_world(**one_predicted, u=u, v=v, ops=tensor)
        if depth is None:  # (Eq. 7, summed in this order, as every published run was)
            error = (
                ops.abs(y_pred[name] - gt[name])
                + ops.abs(X - gt["X"]) + ops.abs(Y - gt["Y"]) + ops.abs(Z - gt["Z"])
            )
        else:
            point = ops.abs(X - gt["X"]) + ops.abs(Y - gt["Y"]) + ops.abs(Z - gt["Z"])
            error = ops.abs(y_pred[name] - gt[name]) + point / depth
        terms.append(ops.mean(error) / n)
    for name in ("X", "Y", "Z"):
        error = ops.abs(y_pred[name] - gt[name])
        terms.append(ops.mean(error if depth is None else error / depth) / n)
    return terms


def uniform_projection_loss(terms):
    """Eq. 7: the mean of the disentangled terms."""
    return ops.sum(ops.stack(terms)) / float(len(terms))


def adaptive_projection_loss(terms, log_variances, floor=None):
    """Eq. 9 with ``alpha_i = exp(-s_i)`` and the regulariser ``sum_i s_i``.

    ``floor`` (one value per term) bounds each ``s_i`` from below: a term
    that reaches 0 (u0 and v0 are constant in the cvgl protocol) would
    otherwise drive its ``s_i`` to minus infinity and the objective with it.
    """
    terms = ops.stack(terms)
    if floor is not None:
        log_variances = ops.maximum(log_variances, floor)
    return ops.sum(ops.exp(-log_variances) * terms + log_variances)


#: How far below its initial value each log-variance s_i may go: alpha_i may
#: grow to at most this factor times its initial value 1 / L_i.
ADAPTIVE_WEIGHT_RANGE = 1e3


def initial_log_variances(terms):
    """``s_i = log L_i`` and the floor ``s_i - log(ADAPTIVE_WEIGHT_RANGE)``.

    Eq. 9 with alpha_i = exp(-s_i) is minimised at alpha_i = 1 / L_i, so
    starting there (from one batch's terms) makes every weighted term start
    at 1: the adaptive weights begin balanced instead of at 1, where terms
    in metres, pixels and radians differ by orders of magnitude. Returns two
    numpy arrays (13,).
    """
    terms = np.maximum(np.asarray(terms, dtype=np.float64), 1e-12)
    start = np.log(terms)
    return start.astype("float32"), (start - math.log(ADAPTIVE_WEIGHT_RANGE)).astype("float32")


def euclidean_loss(y_true, y_pred, epsilon=1e-7):
    """Deep-Homo's loss: the Euclidean distance between the 13-vectors.

    ``sqrt(sum_k (y'_k - y_k)^2)`` per sample, floored at ``epsilon`` inside
    the root so its gradient stays finite at a perfect prediction.
    """
    squared = [
        ops.square(ops.cast(y_pred[name], "float32") - ops.cast(y_true[name], "float32"))
        for name in camera.TARGETS
    ]
    total = ops.sum(ops.concatenate(squared, axis=-1), axis=-1)
    return ops.mean(ops.sqrt(ops.maximum(total, epsilon)))
