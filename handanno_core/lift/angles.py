"""Angle-range rows of the lift (thesis Eq. 5 as rows in mm) and the gradient of their penalty.

Mixed into :class:`handanno_core.lift.problem._Problem`, which sets up ``ak``/``ap``/``ac`` (angle
joints, their parents and children), ``angle_coef``, ``angle_row_w``, ``palm`` and
``hand_sign``.
"""

from __future__ import annotations

import numpy as np

# ---------------------------------------------------------------------------------------- problem
_I1, _I2 = np.array([1, 2, 0]), np.array([2, 0, 1])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of ``(..., 3)`` arrays (np.cross has a large per-call overhead)."""
    return np.take(a, _I1, -1) * np.take(b, _I2, -1) - np.take(a, _I2, -1) * np.take(b, _I1, -1)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product ``(M,)`` of ``(M, 3)`` arrays."""
    return (a * b).sum(axis=1)


def _unit_back(v: np.ndarray, unit: np.ndarray, norm: np.ndarray) -> np.ndarray:
    """Adjoint of ``unit = v / |v|``: ``(I - unit unit^T) v_bar / |v|`` row-wise ``(M, 3)``
    (``v`` the unit's adjoint here, ``norm`` ``(M,)``)."""
    return (v - _dot(unit, v)[:, None] * unit) / norm[:, None]


class _AngleRows:
    """The angle-range rows of :class:`_Problem` (levels of the finger chains, rows, gradient)."""

    def _setup_angle_levels(self) -> None:
        """Constant data for :meth:`_angles`: angle joints grouped by depth along their chain
        (level 0 = a finger's first joint) and the parent's angle index."""
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

        def scatter(plus, minus):  # (J, M): G += S @ v adds v[m] at plus[m], subtracts at minus[m]
            s = np.zeros((self.j, len(plus)))
            s[plus, np.arange(len(plus))] += 1.0
            s[minus, np.arange(len(plus))] -= 1.0
            return s

        self.a_scatter_b = scatter(self.ac, ak)  # bones leaving the angle joints
        self.a_scatter_u = [scatter(ak[idx], np.asarray(self.ap)[idx]) for idx in self.a_levels]
        self.a_coef = np.asarray(self.angle_coef)  # (T, 6, A)

    def _angle_frames(self, X: np.ndarray) -> dict:
        """The local frames of every angle joint for a pose ``X`` ``(J, 3)`` mm.

        The frame follows ``Skeleton.joint_angles``: at a finger's first joint the lateral axis
        is ``normalize(a x n)`` (palm normal ``n``, incoming bone direction ``a``); further along
        it is the parent joint's lateral axis made perpendicular to the incoming bone
        (transported); ``n_perp = lat x a``. Vectorized over fingers: one batch per chain level
        (at most 3 levels). Returns the intermediates :meth:`_angle_grad` needs."""
        w0, i1, l1 = self.palm
        e1 = X[i1] - X[w0]
        e2 = X[l1] - X[w0]
        mvec = _cross(e1, e2)
        mn = max(float(np.linalg.norm(mvec)), 1e-9)
        n = self.hand_sign * mvec / mn
        a_n = len(self.ak)
        A = np.zeros((a_n, 3))
        LAT = np.zeros((a_n, 3))
        U = np.zeros((a_n, 3))
        UN = np.zeros(a_n)
        WN = np.zeros(a_n)
        for idx in self.a_levels:
            u = X[self.ak[idx]] - X[self.ap[idx]]
            un = np.maximum(np.linalg.norm(u, axis=1), 1e-9)
            a = u / un[:, None]
            pi = self.a_parent[idx]
            if pi[0] < 0:  # a level shares one kind (first joint or not): see _setup
                w = _cross(u, n)
            else:
                lp = LAT[pi]
                w = lp - _dot(a, lp)[:, None] * a
            wn = np.maximum(np.linalg.norm(w, axis=1), 1e-9)
            A[idx], LAT[idx], U[idx], UN[idx], WN[idx] = a, w / wn[:, None], u, un, wn
        B = X[self.ac] - X[self.ak]
        bn = np.maximum(np.linalg.norm(B, axis=1), 1e-9)
        return dict(e1=e1, e2=e2, mn=mn, n=n, A=A, LAT=LAT, U=U, UN=UN, WN=WN, B=B, bn=bn)

    def _angles(self, X: np.ndarray, fr: dict | None = None) -> tuple[np.ndarray, dict]:
        """Angle-limit rows ``(4 A T,)`` mm (T tiers of ``angle_coef``; rows ``>= 0`` inside the
        range) for a pose ``X`` ``(J, 3)`` mm, and the frames they were computed in
        (:meth:`_angle_frames`; ``fr`` if already computed for ``X``)."""
        if fr is None:
            fr = self._angle_frames(X)
        B, A, LAT = fr["B"], fr["A"], fr["LAT"]
        s1, s2, s3 = _dot(B, A), _dot(B, _cross(LAT, A)), _dot(B, LAT)
        bn = fr["bn"]
        rows = [
            np.stack([cf0 * s2 - sf0 * s1, sf1 * s1 - cf1 * s2, s3 - bn * sa0, bn * sa1 - s3])
            for cf0, sf0, cf1, sf1, sa0, sa1 in self.angle_coef
        ]
        return np.concatenate([r.ravel() for r in rows]), fr

    def _angle_grad(self, fr: dict, weights: np.ndarray) -> np.ndarray:
        """``sum_r weights_r d row_r / dX`` ``(J, 3)`` for the rows of :meth:`_angles` (``fr`` its
        frames, ``weights`` ``(4 A T,)``): reverse-mode through the rows, the transported frames
        and the palm normal (exact; no Jacobian matrix is formed)."""
        ws = weights.reshape(len(self.angle_coef), 4, -1)
        coef = self.a_coef
        # rows -> s1 = B.a, s2 = B.n_perp, s3 = B.lat, |B|
        g1 = np.sum(-coef[:, 1] * ws[:, 0] + coef[:, 3] * ws[:, 1], axis=0)
        g2 = np.sum(coef[:, 0] * ws[:, 0] - coef[:, 2] * ws[:, 1], axis=0)
        g3 = np.sum(ws[:, 2] - ws[:, 3], axis=0)
        gb = np.sum(-coef[:, 4] * ws[:, 2] + coef[:, 5] * ws[:, 3], axis=0)
        return self._frames_back(fr, g1, g2, g3, gb)

    def _bone_directions(self, fr: dict) -> np.ndarray:
        """``(A, 3)`` the unit bone leaving each angle joint in its frame (along, towards the
        palm, lateral; :meth:`handanno_core.skeleton.Skeleton.bone_directions`) from the frames
        ``fr`` of :meth:`_angle_frames`."""
        B, A, LAT = fr["B"], fr["A"], fr["LAT"]
        s = np.stack([_dot(B, A), _dot(B, _cross(LAT, A)), _dot(B, LAT)], axis=1)
        return s / fr["bn"][:, None]

    def _bone_directions_grad(self, fr: dict, dirs: np.ndarray, d_bar: np.ndarray) -> np.ndarray:
        """``(J, 3)``: the adjoint ``d_bar`` ``(A, 3)`` of :meth:`_bone_directions` (``dirs``)
        taken back to the joints."""
        bn = fr["bn"]
        gb = -np.sum(d_bar * dirs, axis=1) / bn
        return self._frames_back(fr, d_bar[:, 0] / bn, d_bar[:, 1] / bn, d_bar[:, 2] / bn, gb)

    def _frames_back(self, fr, g1, g2, g3, gb) -> np.ndarray:
        """``(J, 3)``: adjoints ``(A,)`` of ``s1 = B.a``, ``s2 = B.n_perp``, ``s3 = B.lat`` and
        ``|B|`` taken back through the transported frames and the palm normal."""
        A, LAT, B, bn, n = fr["A"], fr["LAT"], fr["B"], fr["bn"], fr["n"]
        npp = _cross(LAT, A)
        b_bar = g1[:, None] * A + g2[:, None] * npp + g3[:, None] * LAT
        b_bar += (gb / bn)[:, None] * B
        a_bar = g1[:, None] * B + g2[:, None] * _cross(B, LAT)  # B.(lat x da) = da.(B x lat)
        l_bar = g3[:, None] * B + g2[:, None] * _cross(A, B)  # B.(dlat x a) = dlat.(a x B)
        G = self.a_scatter_b @ b_bar
        n_bar = np.zeros(3)
        for lv in range(len(self.a_levels) - 1, -1, -1):
            idx = self.a_levels[lv]  # children first: their lat feeds on the parent's
            a, u, un, lat = A[idx], fr["U"][idx], fr["UN"][idx], LAT[idx]
            w_bar = _unit_back(l_bar[idx], lat, fr["WN"][idx])
            ab = a_bar[idx]
            pi = self.a_parent[idx]
            if pi[0] < 0:  # w = u x n
                u_bar = _cross(n, w_bar)
                n_bar += np.sum(_cross(w_bar, u), axis=0)
            else:  # w = lp - (a.lp) a
                lp = LAT[pi]
                aw = _dot(a, w_bar)
                l_bar[pi] += w_bar - aw[:, None] * a
                ab = ab - _dot(a, lp)[:, None] * w_bar - aw[:, None] * lp
                u_bar = np.zeros_like(u)
            u_bar = u_bar + _unit_back(ab, a, un)
            G += self.a_scatter_u[lv] @ u_bar
        # n = sign m / |m|, m = e1 x e2
        m_bar = self.hand_sign * (n_bar - float(n @ n_bar) * n) / fr["mn"]
        w0, i1, l1 = self.palm
        e1_bar = _cross(fr["e2"], m_bar)
        e2_bar = _cross(m_bar, fr["e1"])
        G[i1] += e1_bar
        G[l1] += e2_bar
        G[w0] -= e1_bar + e2_bar
        return G
