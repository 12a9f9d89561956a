"""Angle-range rows of the lift (thesis Eq. 5 as inequality rows in mm) and their Jacobians.

Mixed into :class:`handanno_core.lift.problem._Problem`, which sets up ``angle_coef``,
``angle_row_w``, ``palm`` and ``hand_sign``.
"""

from __future__ import annotations

import numpy as np


# ---------------------------------------------------------------------------------------- problem
def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]_x`` with ``[v]_x y = v x y``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of ``(..., 3)`` arrays (np.cross has a large per-call overhead)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


class _AngleRows:
    """The angle-range rows of :class:`_Problem` (levels of the finger chains, rows, Jacobians)."""

    def _setup_angle_levels(self) -> None:
        """Constant data for :meth:`_angles`: angle joints grouped by depth along their chain
        (level 0 = a finger's first joint), the parent's angle index, and the constant
        difference-selection matrices ``D_kp = E_k - E_p`` and ``D_ck`` ``(A, 3, 3J)``."""
        j = self.j
        ak = np.asarray(self.ak)
        index_of = {int(k): i for i, k in enumerate(ak)}
        level = np.zeros(len(ak), dtype=np.int64)
        parent_idx = np.full(len(ak), -1)
        for i, p in enumerate(self.ap):  # angle joints come in topological order
            if int(p) in index_of:
                parent_idx[i] = index_of[int(p)]
                level[i] = level[parent_idx[i]] + 1
        self.a_levels = [np.flatnonzero(level == lv) for lv in range(int(level.max()) + 1)]
        self.a_parent = parent_idx
        eye = np.eye(3)

        def sel(k):
            e = np.zeros((len(k), 3, 3 * j))
            for r, kk in enumerate(k):
                e[r, :, 3 * kk : 3 * kk + 3] += eye
            return e

        self.D_kp = sel(ak) - sel(self.ap)
        self.D_ck = sel(self.ac) - sel(ak)

    def _angles(self, X: np.ndarray, jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Angle-limit rows ``(4A,)`` and their Jacobian ``(4A, J, 3)`` (None if not
        ``jacobian``: the rows alone cost a fraction of it, and the soft penalty needs the
        Jacobian only where some row is negative).

        The local frame follows ``Skeleton.joint_angles``: at a finger's first joint the lateral
        axis is ``normalize(a x n)`` (palm normal ``n``); further along it is the parent joint's
        lateral axis made perpendicular to the incoming bone (transported); ``n_perp = l x a``.
        Derivatives are propagated exactly through the chain and the palm normal. Vectorized over
        fingers: one batch of small matrix products per chain level (at most 3 levels).
        """
        j = self.j
        eye = np.eye(3)
        w0, i1, l1 = self.palm
        e1 = X[i1] - X[w0]
        e2 = X[l1] - X[w0]
        mvec = _cross(e1, e2)
        mn = max(float(np.linalg.norm(mvec)), 1e-9)
        n = self.hand_sign * mvec / mn
        a_n = len(self.ak)
        A = np.zeros((a_n, 3))
        LAT = np.zeros((a_n, 3))
        if jacobian:
            pm = self.hand_sign * (eye - np.outer(n, n)) / mn
            dn = np.zeros((3, j, 3))  # dn/dX
            dn[:, i1] += pm @ -_skew(e2)
            dn[:, l1] += pm @ _skew(e1)
            dn[:, w0] -= dn[:, i1] + dn[:, l1]
            dn = dn.reshape(3, 3 * j)
            DA = np.zeros((a_n, 3, 3 * j))
            DL = np.zeros((a_n, 3, 3 * j))
        for idx in self.a_levels:
            k, p = self.ak[idx], self.ap[idx]
            u = X[k] - X[p]
            un = np.maximum(np.linalg.norm(u, axis=1), 1e-9)
            a = u / un[:, None]
            pi = self.a_parent[idx]
            first = pi[0] < 0  # a level shares one kind (first joint or not): see _setup
            if first:
                w = _cross(u, n)
            else:
                lp = LAT[pi]
                al = np.einsum("mi,mi->m", a, lp)
                w = lp - al[:, None] * a
            wn = np.maximum(np.linalg.norm(w, axis=1), 1e-9)
            lat = w / wn[:, None]
            A[idx], LAT[idx] = a, lat
            if not jacobian:
                continue
            pa = (eye - a[:, :, None] * a[:, None, :]) / un[:, None, None]
            da = pa @ self.D_kp[idx]
            if first:
                sk_u = np.zeros((len(idx), 3, 3))
                sk_u[:, 0, 1], sk_u[:, 0, 2] = -u[:, 2], u[:, 1]
                sk_u[:, 1, 0], sk_u[:, 1, 2] = u[:, 2], -u[:, 0]
                sk_u[:, 2, 0], sk_u[:, 2, 1] = -u[:, 1], u[:, 0]
                dw = -_skew(n) @ self.D_kp[idx] + sk_u @ dn
            else:
                ma = eye - a[:, :, None] * a[:, None, :]
                mb = al[:, None, None] * eye + a[:, :, None] * lp[:, None, :]
                dw = ma @ DL[pi] - mb @ da
            pl = (eye - lat[:, :, None] * lat[:, None, :]) / wn[:, None, None]
            DA[idx], DL[idx] = da, pl @ dw
        npp = _cross(LAT, A)
        B = X[self.ac] - X[self.ak]
        bn = np.maximum(np.linalg.norm(B, axis=1), 1e-9)
        s1 = np.einsum("mi,mi->m", B, A)
        s2 = np.einsum("mi,mi->m", B, npp)
        s3 = np.einsum("mi,mi->m", B, LAT)
        vals = [
            np.stack([cf0 * s2 - sf0 * s1, sf1 * s1 - cf1 * s2, s3 - bn * sa0, bn * sa1 - s3])
            for cf0, sf0, cf1, sf1, sa0, sa1 in self.angle_coef
        ]
        rows = np.concatenate([v.ravel() for v in vals])
        if not jacobian:
            return rows, None
        D = self.D_ck
        g1 = np.einsum("mi,mix->mx", B, DA) + np.einsum("mi,mix->mx", A, D)
        g2 = (
            np.einsum("mi,mix->mx", _cross(A, B), DL)
            + np.einsum("mi,mix->mx", _cross(B, LAT), DA)
            + np.einsum("mi,mix->mx", npp, D)
        )
        g3 = np.einsum("mi,mix->mx", B, DL) + np.einsum("mi,mix->mx", LAT, D)
        gb = np.einsum("mi,mix->mx", B / bn[:, None], D)
        jacs = [
            np.stack(
                [
                    cf0[:, None] * g2 - sf0[:, None] * g1,
                    sf1[:, None] * g1 - cf1[:, None] * g2,
                    g3 - sa0[:, None] * gb,
                    sa1[:, None] * gb - g3,
                ]
            ).reshape(4 * a_n, j, 3)
            for cf0, sf0, cf1, sf1, sa0, sa1 in self.angle_coef
        ]
        return rows, np.concatenate(jacs)
