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


def root_mean_square(values) -> float:
    """The root mean square of a sample (of errors measured on several renders)."""
    return float(np.sqrt(np.mean(np.square(np.asarray(values, np.float64)))))


def quantile(values: np.ndarray, q: float, empty: float = 0.0) -> float:
    """The q-quantile of a sample, ``empty`` for an empty one."""
    return float(np.quantile(values, q)) if len(values) else empty


def block_error(image: np.ndarray, reference: np.ndarray, block: int = 8) -> float:
    """RMS over ``block`` x ``block`` pixel blocks of the difference of the block means of
    ``image`` and ``reference`` (H, W, C), relative to the reference's mean: an image
    comparison whose Monte Carlo noise shrinks with the block size, so that a bias
    (a missing light, other normals) stands out. H and W must be multiples of ``block``."""
    image, reference = np.asarray(image, np.float64), np.asarray(reference, np.float64)
    if image.shape != reference.shape:
        raise ValueError(f"block_error: shapes {image.shape} and {reference.shape} differ")
    h, w = image.shape[:2]
    if h % block or w % block:
        raise ValueError(f"block_error: image size {w}x{h} is not a multiple of {block}")

    def means(img):
        return img.reshape(h // block, block, w // block, block, -1).mean(axis=(1, 3))

    return float(np.sqrt(np.mean((means(image) - means(reference)) ** 2)) / reference.mean())
