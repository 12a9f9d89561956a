"""The lift's optimisation problem for SLSQP: objective, bounds, bone equalities and inequality
rows, in scaled variables ``x = (X - x0) / scale``.
"""

from __future__ import annotations

import copy

import numpy as np

from ..annotation import FrameAnnotation
from ..camera import CameraIntrinsics
from ..pose_prior import PosePrior, mirror_sign
from ..skeleton import Skeleton
from .angles import _AngleRows

# Variable scaling: SLSQP starts its quasi-Newton Hessian at the identity, so each
# unit should move the objective by about the same amount. 1 px of reprojection is ~1.5 mm
# laterally at hand distance (f = 241 px, z = 350 mm), while depth is only weakly determined
# (bones, surface tie-breaker) and gets 10 mm units (fewer SLSQP iterations than uniform 10 mm
# units: benchmarks/results/design_measurements.md).
_SCALE_XY = 1.5  # mm per optimisation unit, x and y
_SCALE_Z = 10.0  # mm per optimisation unit, z (and elastic slacks)


def _angle_tiers(skeleton: Skeleton, right_hand: bool, w_angle: float, w_angle_inner: float):
    """The angle rows' coefficients, per tier a ``(6, A)`` array (cos/sin of the flexion minimum
    and maximum, sin of the abduction minimum and maximum, A angle joints), and the ``(4 A T,)``
    row weights."""
    # soft rows beyond the range real hands were recorded in (weight w_angle) and,
    # optionally, a second tier beyond the narrower anatomical limits (w_angle_inner;
    # default 0: chosen on the tune set, synthetic seed 1 + FPHA Subject_1 mean)
    tiers = [(skeleton.angle_ranges(right_hand), w_angle)]
    lim = skeleton.angle_limits()
    if not right_hand:
        lim = (lim[0], -lim[1][:, ::-1])
    if w_angle_inner > 0 and not all(
        np.array_equal(a, b) for a, b in zip(lim, tiers[0][0], strict=True)
    ):
        tiers.append((lim, w_angle_inner))
    coef, weights = [], []
    for (fl, ab), w in tiers:
        # a flexion range of 170 deg or more is no limit (the two half-plane rows can
        # only express ranges under 180 deg): its rows are switched off
        on = (np.ptp(fl, axis=1) < 170.0).astype(np.float64)
        fl, ab = np.radians(fl), np.radians(ab)
        coef.append(
            np.stack(
                [
                    on * np.cos(fl[:, 0]),
                    on * np.sin(fl[:, 0]),
                    on * np.cos(fl[:, 1]),
                    on * np.sin(fl[:, 1]),
                    np.sin(ab[:, 0]),
                    np.sin(ab[:, 1]),
                ]
            )
        )
        weights.append(np.full(4 * len(skeleton.angle_joints), w))
    return coef, np.concatenate(weights)


class _Problem(_AngleRows):
    """Objective, constraints and their analytic derivatives for one frame (vectorized)."""

    def __init__(
        self,
        annotation: FrameAnnotation,
        d_obs: np.ndarray,
        camera: CameraIntrinsics,
        skeleton: Skeleton,
        bone_lengths_mm: np.ndarray,
        x0_mm: np.ndarray,
        *,
        eps_mm: float,
        angle_limits: bool,
        order_margin_mm: float,
        w_3d: float,
        w_surface: float,
        surface_depth_mm: float = 0.0,
        w_flat: float = 0.0,
        w_free: float,
        soft_bones: float | None,
        right_hand: bool,
        w_angle: float = 1.0,
        w_angle_inner: float = 0.0,
        pose_prior: PosePrior | None = None,
        w_pose: float = 0.0,
        w_accepted: float = 1.0,
    ):
        self.cam = camera
        self.j = skeleton.num_joints
        self.x0 = np.asarray(x0_mm, dtype=np.float64)
        self.bones = skeleton.bones
        self.d = np.asarray(bone_lengths_mm, dtype=np.float64)
        self.soft = soft_bones
        ann = annotation
        self.has2d = ann.has_2d
        self.uv = np.where(self.has2d[:, None], ann.uv_px, 0.0)
        #: (J,) weight of each joint's 2D residual: 1 for a click, ``w_accepted`` for an accepted
        #: guess
        self.w_uv = np.where(ann.accepted, w_accepted, 1.0)
        self.has3d = ann.has_3d
        self.xyz = np.where(self.has3d[:, None], ann.xyz_mm, 0.0)
        #: (J,) weight of each joint's 3D residual: ``w_3d`` for a joint placed by hand, scaled
        #: like its 2D for a shown position the annotator accepted (a review correction's seed)
        self.w_3d = w_3d * self.w_uv
        self.free = ~(self.has2d | self.has3d)
        self.w_free = w_free
        offsets = np.asarray(skeleton.surface_offsets_mm, dtype=np.float64)
        valid_d = np.isfinite(d_obs) & self.has2d
        lo = np.where(valid_d, d_obs + offsets, -np.inf)
        hi = np.where(valid_d & ann.visible, d_obs + offsets + eps_mm, np.inf)
        self.z_lo, self.z_hi = lo, hi
        self.surf_mask = valid_d & ann.visible
        self.surf_target = np.where(self.surf_mask, lo + surface_depth_mm, 0.0)
        self.surf_extra = np.zeros(self.j)
        #: hidden joints with an observed depth (their occluder): lower bound only
        self.hid_mask = valid_d & ~ann.visible
        self.hid_extra = np.zeros(self.j)
        self.w_surface = w_surface
        # hidden joints without a depth order: weak pull towards the parent's depth
        par_all = skeleton.parent_array
        fm = self.has2d & ~ann.visible & (np.asarray(ann.depth_order) == 0) & (par_all >= 0)
        self.flat_k = np.flatnonzero(fm)
        self.flat_p = par_all[self.flat_k]
        self.w_flat = w_flat
        # depth order rows
        sel = (np.asarray(ann.depth_order) != 0) & (par_all >= 0)
        self.ord_k = np.flatnonzero(sel)
        self.ord_p = par_all[self.ord_k]
        self.ord_s = np.asarray(ann.depth_order, dtype=np.float64)[self.ord_k]
        self.margin = order_margin_mm
        # angle rows
        self.use_angles = (
            bool(angle_limits)
            and skeleton.palm_joints is not None
            and len(skeleton.angle_joints) > 0
        )
        # the pose prior (a Gaussian over the bone directions in the angle joints' frames)
        self.use_prior = (
            pose_prior is not None
            and w_pose > 0
            and skeleton.palm_joints is not None
            and len(pose_prior.mean) == 3 * len(skeleton.angle_joints)
        )
        if self.use_prior:
            self.prior = pose_prior
            self.w_pose = w_pose
            self.prior_sign = mirror_sign(right_hand)
        if self.use_angles or self.use_prior:
            k = skeleton.angle_joints
            self.ak = k
            self.ap = par_all[k]
            self.ac = skeleton.angle_children
            self.angle_coef, self.angle_row_w = (
                _angle_tiers(skeleton, right_hand, w_angle, w_angle_inner)
                if self.use_angles
                else ([], np.zeros(0))
            )
            self.palm = skeleton.palm_joints
            self.hand_sign = 1.0 if right_hand else -1.0
            self._setup_angle_levels()
        self.sc3 = np.array([_SCALE_XY, _SCALE_XY, _SCALE_Z])
        self._cache: dict = {}
        self.elastic = False
        self.iv_lo = np.flatnonzero(np.isfinite(lo))  # joints with a lower / upper depth bound
        self.iv_hi = np.flatnonzero(np.isfinite(hi))
        self.w_elastic = 1.0
        self._set_elastic(False)

    def with_surface_extra(self, extra_mm: np.ndarray, hidden: bool = False) -> _Problem:
        """The problem (this one is left unchanged) with visible joints' surface target and upper
        depth bound moved ``extra_mm`` (J,) mm deeper than the offsets say (an inclined finger's
        surface, :func:`handanno_core.lift.surface.inclined_surface_extra_mm`). ``hidden``: the
        hidden joints' lower depth bounds move ``max(extra_mm, 0)`` deeper too (replacing the
        extra this problem already had), a joint covered by its own inclined segment."""
        p = copy.copy(self)
        p._cache = {}
        delta = np.where(self.surf_mask, np.asarray(extra_mm, dtype=np.float64), 0.0)
        delta = delta - self.surf_extra
        p.surf_extra = self.surf_extra + delta
        p.surf_target = self.surf_target + delta
        p.z_hi = np.where(np.isfinite(self.z_hi), self.z_hi + delta, self.z_hi)
        if hidden:
            # a hidden joint covered by its own inclined segment lies at least that segment's
            # inclined depth behind whatever surface is seen at its pixel
            h = np.where(
                self.hid_mask, np.maximum(np.asarray(extra_mm, dtype=np.float64), 0.0), 0.0
            )
            p.hid_extra = h
            p.z_lo = np.where(self.hid_mask, self.z_lo + h - self.hid_extra, p.z_lo)
        return p

    def without_depth(self, joints: np.ndarray) -> _Problem:
        """The problem (this one is left unchanged) without the observed depth of ``joints``
        (S,): no depth interval and no surface target for them (a reading that no pose meets:
        the click lies on another surface, e.g. a finger in front)."""
        p = copy.copy(self)
        p._cache = {}
        drop = np.zeros(self.j, dtype=bool)
        drop[np.asarray(joints, dtype=np.int64)] = True
        p.z_lo = np.where(drop, -np.inf, self.z_lo)
        p.z_hi = np.where(drop, np.inf, self.z_hi)
        p.surf_mask = self.surf_mask & ~drop
        p.iv_lo = np.flatnonzero(np.isfinite(p.z_lo))
        p.iv_hi = np.flatnonzero(np.isfinite(p.z_hi))
        p._set_elastic(False)
        return p

    def with_start(
        self,
        x0_mm: np.ndarray,
        z_inside_mm: np.ndarray,
        *,
        elastic: bool = False,
        weight: float = 1.0,
        joints: np.ndarray | None = None,
    ) -> _Problem:
        """The problem of one solve (this one is left unchanged): variables relative to
        ``x0_mm`` (J, 3) mm, where joints without an elastic slack start at depth ``z_inside_mm``
        (J,) (inside their hard interval); hard, or elastic (see :meth:`_set_elastic`)."""
        p = copy.copy(self)
        p._cache = {}
        p._set_elastic(elastic, weight, joints)
        x0 = np.array(x0_mm, dtype=np.float64)
        x0[:, 2] = np.where(p.slot < 0, z_inside_mm, x0[:, 2])
        p.x0 = x0
        return p

    def _set_elastic(self, on: bool, weight: float = 1.0, joints: np.ndarray | None = None) -> None:
        """Elastic mode: depth intervals become ``z >= lo - s``, ``z <= hi + s`` with slacks
        ``s >= 0`` (one per joint with an interval) costing ``weight`` px^2 per mm (exact L1
        penalty: intervals that can be met are met exactly). ``joints``: only these joints get
        slacks, the others keep their hard bounds (fewer variables and rows, faster iterations)."""
        self.elastic = on
        self.w_elastic = weight
        keep = np.arange(self.j) if joints is None else np.asarray(joints, dtype=np.int64).ravel()
        self.el_lo = np.intersect1d(self.iv_lo, keep) if on else np.zeros(0, dtype=np.int64)
        self.el_hi = np.intersect1d(self.iv_hi, keep) if on else np.zeros(0, dtype=np.int64)
        self.el_joints = np.union1d(self.el_lo, self.el_hi)
        self.slot = np.full(self.j, -1)
        self.slot[self.el_joints] = np.arange(len(self.el_joints))

    def slacks_mm(self, x: np.ndarray) -> np.ndarray:
        """``(S,)`` mm: the elastic slacks at ``x`` (empty outside elastic mode)."""
        return _SCALE_Z * np.asarray(x[3 * self.j : 3 * self.j + self.n_slack])

    @property
    def n_slack(self) -> int:
        return len(self.el_joints) if self.elastic else 0

    @property
    def n_var(self) -> int:
        return 3 * self.j + self.n_slack

    # -- variables: x (3J [+ S],) = (X - x0) / (1.5, 1.5, 10) mm [, slacks / 10 mm]
    def pose(self, x: np.ndarray) -> np.ndarray:
        return self.x0 + self.sc3 * x[: 3 * self.j].reshape(self.j, 3)

    def bounds(self, trust_mm: float = 150.0) -> list[tuple[float | None, float | None]]:
        txy, tz = trust_mm / _SCALE_XY, trust_mm / _SCALE_Z
        b: list[tuple[float | None, float | None]] = []
        for k in range(self.j):
            b.append((-txy, txy))
            b.append((-txy, txy))
            lo, hi = -tz, tz
            if self.slot[k] < 0:  # no slack: the depth interval is a hard bound
                if np.isfinite(self.z_lo[k]):
                    lo = max(lo, (self.z_lo[k] - self.x0[k, 2]) / _SCALE_Z)
                if np.isfinite(self.z_hi[k]):
                    hi = min(hi, (self.z_hi[k] - self.x0[k, 2]) / _SCALE_Z)
                hi = max(hi, lo)
            b.append((lo, hi))
        b.extend([(0.0, tz)] * self.n_slack)
        return b

    # -- objective
    def objective(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        X = self.pose(x)
        g = np.zeros((self.j, 3))
        f = 0.0
        m = self.has2d
        if np.any(m):
            Xm = X[m]
            z = np.maximum(Xm[:, 2], 1e-3)
            u = self.cam.fx * Xm[:, 0] / z + self.cam.cx
            v = self.cam.fy * Xm[:, 1] / z + self.cam.cy
            w = self.w_uv[m]
            ru = u - self.uv[m, 0]
            rv = v - self.uv[m, 1]
            f += 0.5 * float(np.sum(w * (ru**2 + rv**2)))
            ru, rv = w * ru, w * rv
            gx = ru * self.cam.fx / z
            gy = rv * self.cam.fy / z
            gz = -(ru * (u - self.cam.cx) + rv * (v - self.cam.cy)) / z
            g[m] += np.stack([gx, gy, gz], axis=1)
        if np.any(self.has3d):
            w = self.w_3d[self.has3d, None]
            r = (X - self.xyz)[self.has3d]
            f += 0.5 * float(np.sum(w * r**2))
            g[self.has3d] += w * r
        if np.any(self.surf_mask) and self.w_surface > 0:
            r = (X[:, 2] - self.surf_target)[self.surf_mask]
            f += 0.5 * self.w_surface * float(np.sum(r**2))
            g[self.surf_mask, 2] += self.w_surface * r
        if len(self.flat_k) and self.w_flat > 0:
            r = X[self.flat_k, 2] - X[self.flat_p, 2]
            f += 0.5 * self.w_flat * float(np.sum(r**2))
            np.add.at(g[:, 2], self.flat_k, self.w_flat * r)
            np.add.at(g[:, 2], self.flat_p, -self.w_flat * r)
        if np.any(self.free) and self.w_free > 0:
            r = (X - self.x0)[self.free]
            f += 0.5 * self.w_free * float(np.sum(r**2))
            g[self.free] += self.w_free * r
        if self.soft is not None:
            c, jac = self._bone_eq(X)
            f += 0.5 * self.soft * float(np.sum(c**2))
            g += self.soft * np.einsum("b,bjk->jk", c, jac)
        frames = self._angle_frames(X) if (self.use_angles or self.use_prior) else None
        if self.use_prior:
            dirs = self._bone_directions(frames)
            r = self.prior.residuals((dirs * self.prior_sign).ravel())
            f += 0.5 * self.w_pose * float(r @ r)
            d_bar = (self.w_pose * (r @ self.prior.sqrt_precision)).reshape(-1, 3)
            g += self._bone_directions_grad(frames, dirs, d_bar * self.prior_sign)
        if self.use_angles:
            v, frames = self._angles(X, frames)
            short = np.minimum(v, 0.0)  # mm beyond the range (rows are >= 0 inside)
            ws = self.angle_row_w * short
            if np.any(ws):  # inside every range the penalty and its gradient are 0
                f += 0.5 * float(np.sum(self.angle_row_w * short**2))
                g += self._angle_grad(frames, ws)
        grad = (self.sc3 * g).ravel()
        if self.elastic:
            sl = x[3 * self.j :]
            f += self.w_elastic * _SCALE_Z * float(np.sum(sl))
            grad = np.concatenate([grad, np.full(len(sl), self.w_elastic * _SCALE_Z)])
        return f, grad

    # -- constraints (in mm), Jacobians w.r.t. joints (rows, J, 3)
    def _bone_eq(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, c = self.bones[:, 0], self.bones[:, 1]
        v = X[c] - X[p]
        n = np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        jac = np.zeros((len(p), self.j, 3))
        rows = np.arange(len(p))
        unit = v / n[:, None]
        jac[rows, c] = unit
        jac[rows, p] -= unit
        return n - self.d, jac

    def _cached(self, name: str, x: np.ndarray):
        """SLSQP asks for a constraint and its Jacobian at the same x: evaluate once."""
        hit = self._cache.get(name)
        if hit is not None and np.array_equal(hit[0], x):
            return hit[1]
        X = self.pose(x)
        val = self._bone_eq(X) if name == "eq" else self._ineq(X)
        self._cache[name] = (x.copy(), val)
        return val

    def eq(self, x: np.ndarray) -> np.ndarray:
        return self._cached("eq", x)[0]

    def eq_jac(self, x: np.ndarray) -> np.ndarray:
        jac = (self._cached("eq", x)[1] * self.sc3).reshape(len(self.d), -1)
        if self.n_slack:
            jac = np.hstack([jac, np.zeros((len(jac), self.n_slack))])
        return jac

    def _ineq(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        vals = []
        jacs = []
        if len(self.ord_k):
            r = len(self.ord_k)
            val = self.ord_s * (X[self.ord_k, 2] - X[self.ord_p, 2]) - self.margin
            jac = np.zeros((r, self.j, 3))
            rows = np.arange(r)
            jac[rows, self.ord_k, 2] = self.ord_s
            jac[rows, self.ord_p, 2] -= self.ord_s
            vals.append(val)
            jacs.append(jac)
        if not vals:
            return np.zeros(0), np.zeros((0, self.j, 3))
        return np.concatenate(vals), np.concatenate(jacs, axis=0)

    def ineq(self, x: np.ndarray) -> np.ndarray:
        val = self._cached("ineq", x)[0]
        if self.elastic:
            X = self.pose(x)
            sl = _SCALE_Z * x[3 * self.j :]
            lo = X[self.el_lo, 2] - self.z_lo[self.el_lo] + sl[self.slot[self.el_lo]]
            hi = self.z_hi[self.el_hi] - X[self.el_hi, 2] + sl[self.slot[self.el_hi]]
            val = np.concatenate([val, lo, hi])
        return val

    def ineq_jac(self, x: np.ndarray) -> np.ndarray:
        jac = self._cached("ineq", x)[1]
        # (rows, J, 3) -> (rows, 3J); explicit width, since there may be no rows (elastic mode
        # with every depth bound turned into a slack row below)
        jac = (jac * self.sc3).reshape(jac.shape[0], 3 * self.j)
        if self.elastic:
            ns = self.n_slack
            jac = np.hstack([jac, np.zeros((len(jac), ns))])
            nl, nh = len(self.el_lo), len(self.el_hi)
            extra = np.zeros((nl + nh, self.n_var))
            extra[np.arange(nl), 3 * self.el_lo + 2] = _SCALE_Z
            extra[np.arange(nl), 3 * self.j + self.slot[self.el_lo]] = _SCALE_Z
            extra[nl + np.arange(nh), 3 * self.el_hi + 2] = -_SCALE_Z
            extra[nl + np.arange(nh), 3 * self.j + self.slot[self.el_hi]] = _SCALE_Z
            jac = np.vstack([jac, extra])
        return jac

    def num_ineq(self) -> int:
        n = len(self.ord_k)
        if self.elastic:
            n += len(self.el_lo) + len(self.el_hi)
        return n
