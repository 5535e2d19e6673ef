"""Measures shared by the verification tools: angles between normals, float32 ULPs of
points, and robust summaries of error samples."""

from __future__ import annotations

import numpy as np


def angle_deg(a: np.ndarray, b: np.ndarray, oriented: bool = True) -> np.ndarray:
    """Angle in degrees between the rows of (N, 3) ``a`` and ``b`` (atan2 of the cross and
    dot products: accurate at 0 and 180 degrees); ``oriented=False`` ignores the sign."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    dot = np.sum(a * b, axis=1)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1),
                                 dot if oriented else np.abs(dot)))


def ulp_spacing(p: np.ndarray) -> np.ndarray:
    """The float32 spacing (ULP) at |p|, per row of (N, 3) points."""
    return np.spacing(np.linalg.norm(p, axis=1).astype(np.float32)).astype(np.float64)


def ulp_error(p: np.ndarray, p_ref: np.ndarray) -> np.ndarray:
    """|p - p_ref| per row, in units of the float32 ULP of |p_ref|."""
    return np.linalg.norm(p - p_ref, axis=1) / ulp_spacing(p_ref)


def quantile(values: np.ndarray, q: float, empty: float = 0.0) -> float:
    """The q-quantile of a sample, ``empty`` for an empty one."""
    return float(np.quantile(values, q)) if len(values) else empty
