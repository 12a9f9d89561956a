"""The rigid motion that best takes one set of 3D points onto another (Kabsch): :func:`kabsch`."""

from __future__ import annotations

import numpy as np

__all__ = ["kabsch"]


def kabsch(a_mm: np.ndarray, b_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(rot, ca, cb)``: the rotation ``rot`` (3, 3) and the centroids ``ca``, ``cb`` (3,) mm of
    the rigid motion ``x -> (x - ca) @ rot.T + cb`` that takes the points ``a_mm`` (K, 3) closest
    to ``b_mm`` (K, 3) in least squares (a proper rotation, no mirror). None where the points do
    not fix a rotation: fewer than 3, or nearly collinear (the cross-covariance's second singular
    value under 1e-3 of its first)."""
    a = np.asarray(a_mm, dtype=np.float64)
    b = np.asarray(b_mm, dtype=np.float64)
    if len(a) < 3:
        return None
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, sv, vt = np.linalg.svd((a - ca).T @ (b - cb))
    if sv[1] < 1e-3 * max(sv[0], 1e-9):
        return None
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T, ca, cb
