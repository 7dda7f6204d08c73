"""Camera intrinsics in a sensor.yaml: one key convention for every system (EuRoC / Kalibr), one reader.

Written (EuRoC's ``cam0/sensor.yaml``; Kalibr's camchain uses the same meaning, with ``distortion_coeffs`` and
``radtan``)::

    camera_model: pinhole
    intrinsics: [fu, fv, cu, cv]                 # px
    distortion_model: radial-tangential
    distortion_coefficients: [k1, k2, p1, p2]    # OpenCV order; [k1, k2, p1, p2, k3] when k3 != 0
    resolution: [width, height]                  # px (omitted when the sensor.yaml never had one)

Kalibr's and EuRoC's radial-tangential model has four coefficients.  Our OpenCV-based models carry a fifth,
``k3``; it is written only when it is not zero, as the fifth element in OpenCV's order, so a file that needs it
is refused by Kalibr (a model it does not have) instead of silently losing it.

Read: these keys, and the older ones still found in recordings (``K`` / ``dist``, ``width_px`` of the scan
system's line cameras; ``camera_matrix`` / ``dist_coeffs`` of the tracker's camera).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfcal.io.recording import RecordingError

RADTAN = ("radial-tangential", "radtan")


@dataclass
class CameraIntrinsics:
    """Pinhole camera with OpenCV's radial-tangential distortion (``dist``: k1, k2, p1, p2, k3)."""

    K: np.ndarray  # (3, 3) camera matrix, px
    dist: np.ndarray  # (5,) k1, k2, p1, p2, k3
    resolution: tuple[int, int] | None = None  # (width, height), px


def camera_keys(K, dist, resolution=None) -> dict:
    """The sensor.yaml keys of a pinhole camera with OpenCV distortion ``dist`` (4 or 5 coefficients)."""
    K = np.asarray(K, dtype=float)
    d = np.zeros(5)
    d[:len(dist)] = np.asarray(dist, dtype=float)
    out = {"camera_model": "pinhole",
           "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
           "distortion_model": "radial-tangential",
           "distortion_coefficients": [float(v) for v in (d if d[4] != 0.0 else d[:4])]}
    if resolution is not None:
        out["resolution"] = [int(resolution[0]), int(resolution[1])]
    return out


def read_camera(meta: dict, where: str = "sensor.yaml") -> CameraIntrinsics:
    """Camera intrinsics from a sensor.yaml dict, in the current keys or the older ones (module notes)."""
    if "intrinsics" in meta:
        if meta.get("camera_model", "pinhole") != "pinhole":
            raise RecordingError(f"{where}: camera_model {meta.get('camera_model')!r} is not supported (pinhole only)")
        if meta.get("distortion_model", "radial-tangential") not in RADTAN:
            raise RecordingError(f"{where}: distortion_model {meta.get('distortion_model')!r} is not supported "
                                 "(radial-tangential only)")
        fu, fv, cu, cv = _numbers(meta["intrinsics"], 4, "intrinsics", where)
        K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
        dist = meta.get("distortion_coefficients", [0.0] * 4)
    elif "K" in meta or "camera_matrix" in meta:
        name = "K" if "K" in meta else "camera_matrix"
        K = np.asarray(meta[name], dtype=float)
        if K.shape != (3, 3):
            raise RecordingError(f"{where}: {name} must be a 3x3 matrix, got shape {K.shape}")
        dist = meta.get("dist", meta.get("dist_coeffs", [0.0] * 4))
    else:
        raise RecordingError(f"{where}: no camera intrinsics (need 'intrinsics' and 'distortion_coefficients')")
    dist = np.asarray(dist, dtype=float).ravel()
    if len(dist) not in (4, 5):
        raise RecordingError(f"{where}: distortion needs 4 or 5 coefficients (k1, k2, p1, p2[, k3]), got {len(dist)}")
    resolution = meta.get("resolution")
    if resolution is None and "width_px" in meta:
        resolution = (meta["width_px"], 1)  # the scan system's line cameras: one sensor row
    if resolution is not None:
        resolution = tuple(int(v) for v in _numbers(resolution, 2, "resolution", where))
    return CameraIntrinsics(K, np.concatenate([dist, np.zeros(5 - len(dist))]), resolution)


def _numbers(values, count: int, key: str, where: str) -> list[float]:
    values = np.asarray(values, dtype=float).ravel()
    if len(values) != count or not np.all(np.isfinite(values)):
        raise RecordingError(f"{where}: {key} must be {count} finite numbers, got {values.tolist()}")
    return values.tolist()
