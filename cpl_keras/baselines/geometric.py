"""The "Geometric" baseline: classical two-view calibration with OpenCV.

The traditional method the paper says it beats but never shows. On one stereo
pair (left, right) it does:

1. **Matches**: SIFT keypoints (or ORB) on both images (upsampled by
   ``upscale`` first, because 112-pixel images hold few keypoints), Lowe's
   ratio test, then a robust fundamental matrix ``F`` (``x_right^T F x_left = 0``)
   by RANSAC (``cv2.findFundamentalMat``).
2. **Focal length** by Bougnoux's formula with the principal point at the image
   centre and square pixels. The formula gives one focal length per camera;
   both cameras of a rig share their intrinsics here, so the estimate is the
   geometric mean of the two when both are real, else the real one.
3. **Pose**: the essential matrix ``E = K^T F K`` and ``cv2.recoverPose`` give
   the right camera's rotation and the *direction* of its translation. They
   are converted from OpenCV's camera axes (x right, y down, z forward) to the
   project's (x forward, y left, z up) and inverted to the project's extrinsics
   convention (right camera pose in the left camera frame,
   ``P_left = R P_right + t``), so pitch has the sign of paper Eq. 5 (positive
   tilts the optical axis down): ``pitch = asin(-R[2, 0])`` for
   ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (``frames.rotation_matrix``).
4. **Disparity** at the projection pixel ``(u, v)`` of the right image, from
   ``cv2.StereoSGBM`` run on the horizontally flipped, swapped pair (so the
   disparity map is the right image's: the point at right pixel ``u`` is at
   left pixel ``u + d``), as the median of the valid values in a 5x5 window.
   The pair is not rectified first, so this is meaningful for near-rectified
   lateral rigs only, like the release's StereoBM label.

How each of the 10 parameters (and X, Y, Z) is obtained:

==========  ===============================================================
fx, fy      Bougnoux's formula (fx = fy: square pixels are assumed).
u0, v0      Not estimated: the image centre (W/2, H/2) is assumed
            (Bougnoux's formula needs the principal point as an input).
pitch       From recoverPose's rotation (step 3).
tx, ty, tz  Direction from recoverPose; the scale is unobservable from two
            uncalibrated views (translation is known up to scale), so the
            output is ``baseline_prior * direction``.
baseline    Unobservable (metric scale): the output is ``baseline_prior``
            (the training-set mean baseline when evaluated against a run,
            else 1 m).
disparity   SGBM at (u, v) (step 4).
X, Y, Z     The camera equations (Eqs. 4a-5c, ``camera.image_to_world``)
            applied to the estimates above at pixel (u, v).
==========  ===============================================================

Failures are never silent. Each stage that fails falls back to a stated
prior (``priors``: by default a 60-degree field of view, pitch 0, a lateral
rig direction (0, -1, 0), and for disparity the median valid disparity of
the whole image, else the prior disparity), and is counted in the result's
``status`` flags; ``failure_report`` turns the flags of a data set into
failure rates. The stages:

* ``few_matches``: fewer than ``min_matches`` ratio-test matches, or RANSAC
  found no fundamental matrix with at least 8 inliers (focal and pose fall
  back);
* ``imaginary_focal``: Bougnoux's ``f^2 <= 0`` for both cameras, or
  ``implausible_focal``: a field of view outside [10, 170] degrees (focal
  falls back; the pose is still recovered with the fallback focal);
* ``pose_failed``: recoverPose kept fewer than 5 points (pitch and
  translation direction fall back);
* ``no_disparity``: no valid SGBM value in the window (disparity falls back).

Bougnoux's formula is degenerate when the two optical axes are coplanar, e.g.
for a purely lateral, rectified rig with no rotation: there the focal length
is ill-conditioned and often imaginary. That is a property of the method, and
the reason the failure rate is reported.
"""

from __future__ import annotations

import math

import numpy as np

from cpl_keras.camera import TARGETS, focal_from_fov, fov_from_focal, image_to_world
from cpl_keras.stereo_camera import StereoCamera

#: Failure flags counted by ``failure_report``.
FAILURE_FLAGS = (
    "few_matches", "imaginary_focal", "implausible_focal", "pose_failed", "no_disparity",
)
#: Prior field of view (degrees) used when the focal length cannot be estimated.
DEFAULT_FOV_DEG = 60.0
#: Smallest grey-level standard deviation of a 5x5 block SGBM may match.
MIN_TEXTURE_STD = 2.0
#: Accepted field-of-view range (degrees) of a Bougnoux focal length.
FOV_RANGE_DEG = (10.0, 170.0)

def _cv2():
    import cv2

    return cv2


def _skew(vector):
    x, y, z = vector
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def bougnoux_focal_squared(F, p1, p2):
    """Bougnoux's formula: the squared focal length of the FIRST camera.

    ``F`` satisfies ``x2^T F x1 = 0``; ``p1``, ``p2`` are the principal points
    (pixels) of the two cameras. Square pixels and zero skew are assumed::

        f1^2 = -(p2^T [e2]x I F p1)(p1^T F^T p2) / (p2^T [e2]x I F I F^T p2)

    with ``I = diag(1, 1, 0)`` and ``e2`` the epipole in image 2
    (``F^T e2 = 0``). Call with ``F.T`` (and swapped points) for the second
    camera. Returns nan when the formula is 0/0 (degenerate configuration).
    """
    F = np.asarray(F, dtype=np.float64)
    p1 = np.array([p1[0], p1[1], 1.0])
    p2 = np.array([p2[0], p2[1], 1.0])
    _, _, vt = np.linalg.svd(F.T)
    e2 = vt[-1]
    I = np.diag([1.0, 1.0, 0.0])  # noqa: E741  (the formula's name)
    numerator = -(p2 @ _skew(e2) @ I @ F @ p1) * (p1 @ F.T @ p2)
    denominator = p2 @ _skew(e2) @ I @ F @ I @ F.T @ p2
    if denominator == 0.0 or not np.isfinite(denominator):
        return math.nan
    return float(numerator / denominator)


def default_priors(width, height):
    """The fallback values of a ``width`` x ``height`` image (see module doc)."""
    focal = float(focal_from_fov(math.radians(DEFAULT_FOV_DEG), width))
    return {
        "fx": focal, "fy": focal, "baseline": 1.0, "disparity": 1.0,
        "pitch": 0.0, "direction": (0.0, -1.0, 0.0),
    }


def _gray(image):
    cv2 = _cv2()
    image = np.asarray(image)
    if image.ndim == 3:
        return cv2.cvtColor(image.astype(np.uint8), cv2.COLOR_RGB2GRAY)
    return image.astype(np.uint8)


def match_points(left, right, detector="sift", upscale=2.0, ratio=0.8):
    """Ratio-test matches between two images: (N, 2) float arrays in pixels
    of the original images (left points, right points)."""
    cv2 = _cv2()
    gray_l, gray_r = _gray(left), _gray(right)
    if upscale != 1.0:
        size = (int(round(gray_l.shape[1] * upscale)), int(round(gray_l.shape[0] * upscale)))
        gray_l = cv2.resize(gray_l, size, interpolation=cv2.INTER_CUBIC)
        gray_r = cv2.resize(gray_r, size, interpolation=cv2.INTER_CUBIC)
    if detector == "sift":
        features = cv2.SIFT_create()
        norm = cv2.NORM_L2
    elif detector == "orb":
        features = cv2.ORB_create(nfeatures=2000, edgeThreshold=15, patchSize=15)
        norm = cv2.NORM_HAMMING
    else:
        raise ValueError(f"unknown detector '{detector}' (use 'sift' or 'orb')")
    kp_l, des_l = features.detectAndCompute(gray_l, None)
    kp_r, des_r = features.detectAndCompute(gray_r, None)
    if des_l is None or des_r is None or len(kp_l) < 2 or len(kp_r) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pairs = cv2.BFMatcher(norm).knnMatch(des_l, des_r, k=2)
    good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    # pixel centres: x_orig = (x_up + 0.5) / upscale - 0.5
    pts_l = np.array([kp_l[m.queryIdx].pt for m in good], dtype=np.float64).reshape(-1, 2)
    pts_r = np.array([kp_r[m.trainIdx].pt for m in good], dtype=np.float64).reshape(-1, 2)
    return (pts_l + 0.5) / upscale - 0.5, (pts_r + 0.5) / upscale - 0.5


def right_disparity_map(left, right, max_disparity=None):
    """Disparity map of the RIGHT image (float32 px, nan = invalid) from SGBM.

    The point at right pixel ``(u, v)`` is at left pixel ``(u + d, v)``
    (the project's convention). Computed by running SGBM on the horizontally
    flipped pair with the images swapped; the search range is symmetric,
    ``[-max_disparity, max_disparity)``, so a right camera on the left side
    (negative disparity) is handled too.
    """
    cv2 = _cv2()
    gray_l, gray_r = _gray(left), _gray(right)
    width = gray_l.shape[1]
    if max_disparity is None:
        max_disparity = 16 * max(1, int(math.ceil(width / 4 / 16)))
    block = 5
    matcher = cv2.StereoSGBM_create(
        minDisparity=-max_disparity, numDisparities=2 * max_disparity, blockSize=block,
        P1=8 * block * block, P2=32 * block * block, uniquenessRatio=10,
        speckleWindowSize=50, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM,
    )
    raw = matcher.compute(np.ascontiguousarray(gray_r[:, ::-1]),
                          np.ascontiguousarray(gray_l[:, ::-1]))
    raw = raw[:, ::-1].astype(np.float32)
    invalid = raw <= (-max_disparity - 1) * 16
    # textureless blocks match anywhere: mark them invalid
    gray = gray_r.astype(np.float32)
    mean = cv2.blur(gray, (block, block))
    local_std = np.sqrt(np.maximum(cv2.blur(gray * gray, (block, block)) - mean * mean, 0.0))
    invalid |= local_std < MIN_TEXTURE_STD
    disparity = raw / 16.0
    disparity[invalid] = np.nan
    return disparity


def _disparity_at(disparity_map, u, v, radius=2):
    h, w = disparity_map.shape
    iu = int(np.clip(round(float(u)), 0, w - 1))
    iv = int(np.clip(round(float(v)), 0, h - 1))
    window = disparity_map[max(0, iv - radius):iv + radius + 1,
                           max(0, iu - radius):iu + radius + 1]
    valid = window[np.isfinite(window)]
    if valid.size:
        return float(np.median(valid)), True
    valid = disparity_map[np.isfinite(disparity_map)]
    if valid.size:
        return float(np.median(valid)), False
    return math.nan, False


def calibrate_from_matches(pts_left, pts_right, width, height, priors=None, min_matches=12,
                           ransac_threshold=1.0):
    """Steps 1-3 of the module doc on point matches (pixels, (N, 2) each).

    Returns ``(result, status)``: ``result`` has ``fx``, ``fy``, ``u0``,
    ``v0``, ``pitch`` and the unit translation ``direction`` (project axes,
    right camera centre in the left camera frame); ``status`` has the failure
    flags of these steps, ``num_matches``, ``num_inliers`` and ``focal_sq``
    (Bougnoux's two values, left and right camera).
    """
    cv2 = _cv2()
    pts_l = np.asarray(pts_left, dtype=np.float64).reshape(-1, 2)
    pts_r = np.asarray(pts_right, dtype=np.float64).reshape(-1, 2)
    cx, cy = width / 2.0, height / 2.0
    prior = default_priors(width, height)
    prior.update(priors or {})
    status = {flag: False for flag in FAILURE_FLAGS}
    status.update(num_matches=int(len(pts_l)), num_inliers=0, focal_sq=[math.nan, math.nan])

    # 1. a robust fundamental matrix, x_right^T F x_left = 0
    F, inliers = None, None
    if len(pts_l) >= max(8, min_matches):
        cv2.setRNGSeed(0)                      # RANSAC samples: same pair, same answer
        F, mask = cv2.findFundamentalMat(pts_l, pts_r, cv2.FM_RANSAC, ransac_threshold, 0.999)
        if F is not None and F.shape == (3, 3) and mask is not None and int(mask.sum()) >= 8:
            inliers = mask.ravel().astype(bool)
            status["num_inliers"] = int(inliers.sum())
        else:
            F = None
    if F is None:
        status["few_matches"] = True

    # 2. focal length (Bougnoux), principal point at the centre
    focal = float(prior["fx"]) if F is None else _focal(F, cx, cy, width, prior["fx"], status)

    # 3. pose: the rig at unit baseline (the translation's length is unobservable)
    direction = np.asarray(prior["direction"], dtype=np.float64)
    rig = StereoCamera(fx=focal, fy=focal, u0=cx, v0=cy, width=width, height=height,
                       baseline=1.0, pitch=prior["pitch"], tx=direction[0], ty=direction[1],
                       tz=direction[2])
    found = None if F is None else _recover_pose(rig, F, pts_l[inliers], pts_r[inliers])
    status["pose_failed"] = found is None
    if found is not None:
        rig = found
        direction = np.array([rig.tx, rig.ty, rig.tz]) / max(rig.baseline, 1e-12)
    result = {"fx": rig.fx, "fy": rig.fy, "u0": rig.u0, "v0": rig.v0, "pitch": rig.pitch,
              "direction": direction}
    return result, status


def _focal(F, cx, cy, width, fallback, status):
    """Step 2 of the module doc: Bougnoux's focal length of both cameras
    (their geometric mean), principal point ``(cx, cy)``; ``fallback`` when
    imaginary or implausible (``status`` says which, and holds both values)."""
    p = (cx, cy)
    f_left_sq = bougnoux_focal_squared(F, p, p)
    f_right_sq = bougnoux_focal_squared(F.T, p, p)
    status["focal_sq"] = [f_left_sq, f_right_sq]
    real = [f for f in (f_left_sq, f_right_sq) if np.isfinite(f) and f > 0]
    if not real:
        status["imaginary_focal"] = True
        return float(fallback)
    candidate = float(np.prod(np.sqrt(real)) ** (1.0 / len(real)))
    fov = math.degrees(float(fov_from_focal(candidate, width)))
    if FOV_RANGE_DEG[0] <= fov <= FOV_RANGE_DEG[1]:
        return candidate
    status["implausible_focal"] = True
    return float(fallback)


def _recover_pose(rig, F, pts_left, pts_right):
    """Step 3 of the module doc: the rig (intrinsics of ``rig``) with the
    right camera's pose from the essential matrix ``K^T F K`` of the inlier
    matches (``cv2.recoverPose``), its baseline the translation's length
    (unobservable: 1); None when fewer than 5 points support it."""
    K = rig.K
    good, R_cv, t_cv, _ = _cv2().recoverPose(K.T @ F @ K, pts_left, pts_right, K)
    if int(good) < 5:
        return None
    # OpenCV's X_right = R_cv X_left + t_cv, as the right camera's pose in the left frame
    return StereoCamera.from_opencv_pose(R_cv, t_cv, K, rig.width, rig.height)


def estimate_pair(left, right, u=None, v=None, priors=None, detector="sift", upscale=2.0,
                  min_matches=12, ransac_threshold=1.0):
    """The 13 targets of one pair by classical geometry (see module doc).

    ``left``, ``right``: uint8 images (H, W, 3) RGB or (H, W). ``(u, v)``: the
    projection pixel in the right image (default: the image centre).
    ``priors``: fallback values, see ``default_priors``. Returns
    ``(params, status)``: ``params`` maps each name of ``camera.TARGETS`` to a
    float, ``status`` has a bool per ``FAILURE_FLAGS`` name plus
    ``num_matches``, ``num_inliers``, ``focal_sq`` (the two Bougnoux values).
    """
    left = np.asarray(left)
    right = np.asarray(right)
    if left.shape != right.shape or left.ndim not in (2, 3):
        raise ValueError(
            f"left and right must be images of one shape, got {left.shape} and {right.shape}"
        )
    height, width = left.shape[:2]
    prior = default_priors(width, height)
    prior.update(priors or {})
    pts_l, pts_r = match_points(left, right, detector=detector, upscale=upscale)
    geometry, status = calibrate_from_matches(pts_l, pts_r, width, height, prior,
                                              min_matches, ransac_threshold)
    u = geometry["u0"] if u is None else float(u)
    v = geometry["v0"] if v is None else float(v)

    # 4. disparity at the projection pixel of the right image
    disparity, found = _disparity_at(right_disparity_map(left, right), u, v)
    status["no_disparity"] = not found
    if not np.isfinite(disparity):
        disparity = float(prior["disparity"])

    baseline = float(prior["baseline"])
    tx, ty, tz = (baseline * geometry["direction"]).tolist()
    fx, fy, u0, v0, pitch = (geometry[k] for k in ("fx", "fy", "u0", "v0", "pitch"))
    params = {
        "fx": fx, "fy": fy, "u0": u0, "v0": v0, "baseline": baseline,
        "disparity": disparity, "tx": tx, "ty": ty, "tz": tz, "pitch": pitch,
    }
    X, Y, Z = image_to_world(fx, fy, u0, v0, baseline, disparity, pitch, tx, ty, tz, u, v)
    params.update(X=float(X), Y=float(Y), Z=float(Z))
    return params, status


def predict_pairs(left_images, right_images, u=None, v=None, priors=None, **kwargs):
    """``estimate_pair`` over a batch: ``(predictions, statuses)`` with
    ``predictions[name]`` a float64 array (n,) for every name of TARGETS."""
    n = len(left_images)
    predictions = {name: np.zeros(n) for name in TARGETS}
    statuses = []
    for i in range(n):
        ui = None if u is None else u[i]
        vi = None if v is None else v[i]
        params, status = estimate_pair(left_images[i], right_images[i], ui, vi, priors, **kwargs)
        for name in TARGETS:
            predictions[name][i] = params[name]
        statuses.append(status)
    return predictions, statuses


def predict_file(stereo_file, indices=None, priors=None, block=64, **kwargs):
    """Geometric predictions for pairs ``indices`` of an open ``StereoFile``
    (all by default), at each pair's stored projection pixel (u, v), or the
    release's (``u_released``, ``v_released``) in a file imported from it."""
    if indices is None:
        indices = np.arange(stereo_file.num_pairs)
    indices = np.asarray(indices, dtype=np.int64)
    labels = stereo_file.labels
    u_all = (labels["u"] if "u" in labels else labels["u_released"])[indices]
    v_all = (labels["v"] if "v" in labels else labels["v_released"])[indices]
    parts, statuses = [], []
    for start in range(0, len(indices), block):
        chunk = indices[start:start + block]
        left, right = stereo_file.read_pairs(chunk)
        pred, stat = predict_pairs(left, right, u_all[start:start + block],
                                   v_all[start:start + block], priors, **kwargs)
        parts.append(pred)
        statuses.extend(stat)
    predictions = {name: np.concatenate([p[name] for p in parts]) if parts else np.zeros(0)
                   for name in TARGETS}
    return predictions, statuses


def failure_report(statuses):
    """Counts and rates of each failure flag over a list of statuses, plus the
    share of pairs where every stage succeeded."""
    n = len(statuses)
    report = {"num_pairs": n}
    for flag in FAILURE_FLAGS:
        count = int(sum(bool(s[flag]) for s in statuses))
        report[flag] = {"count": count, "rate": count / n if n else math.nan}
    all_ok = sum(not any(s[flag] for flag in FAILURE_FLAGS) for s in statuses)
    report["all_stages_ok"] = {"count": int(all_ok), "rate": all_ok / n if n else math.nan}
    return report
