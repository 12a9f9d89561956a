"""Global refinement of all frames' 3D joints (thesis Eq. 4), done properly.

One robust least-squares problem over every frame of the sequence:

``E = Σ λ_app   ρ_W(appearance sample)        7×7 patch per joint, mm (Welsch)
    + Σ λ_acc   ρ_H(‖X[i+1,k] − 2X[i,k] + X[i−1,k]‖)  three consecutive frames, camera coords, mm
    + Σ λ_temp  ρ_H(‖X[i+1,k] − X[i,k]‖)       consecutive frames (off by default), mm
    + Σ λ_proj  ½‖π(X[r,k]) − l[r,k]‖²          reference frames' annotated 2D, px
    + Σ λ_depth ρ_W(depth-band violation)       Eq. 3 band behind the observed surface, mm
    + Σ λ_angle ½(joint-angle violation)²       skeleton.angle_limits, degrees
    + Σ λ_init  ρ_H(‖X − X_init‖)               weak pull to the initialization, mm``

(ρ_H Huber, ρ_W Welsch, both ≈ ½r² for small r), i.e. residuals weighted by ``√λ`` in the units
stated; default λ and why in :class:`RefineWeights`. The reference frames are held at their
initialization, the lift of what a person annotated (``hold_references``): they enter the other
frames' terms (temporal neighbours, appearance templates) unchanged, and ``λ_proj`` matters only
when they are released.

**Bone lengths are hard constraints** through the parameterization: each frame is a root position
(3) plus one unit direction per bone (updated on the sphere through a 2-D tangent step), with the
bone lengths fixed to ``bone_lengths_mm``; joints are ``X_k = root + Σ_{b on path to k} L_b·u_b``.
The final bone violation is therefore round-off (reported in ``bone_violation_max_mm``).

**Appearance** (Lucas-Kanade style, no precomputed per-pixel maps): for frame ``i`` and joint ``k``
the crop of frame ``i`` is sampled bilinearly on a 7×7 grid (2 crop px spacing) around the joint's
current projection; each sample is turned into depth in mm *relative to the joint's own depth*
(``z_c + crop·cube/2 − Z_ik``, clipped to ±``appearance_clip_mm`` so background is a constant) and
compared with the same patch taken once, at the start, around the annotated 2D position in the
crop of the frame's closest reference (relative to that reference joint's depth). The Jacobian
uses the analytic gradient of the bilinear interpolant. The same crops give the observed depth
``D`` at each projection for the depth band (``D + offset_k ≤ Z ≤ D + offset_k + eps``; the lower
side holds for every joint that projects onto the hand, the upper side only for joints visible in
the frame's closest reference annotation; both sides use a redescending loss because a joint whose
projection lands on another surface must not be dragged onto it).

**Solver**: Levenberg-Marquardt with IRLS weights for the robust terms. The normal equations are
block-banded in time (blocks of ``3 + 2B`` parameters per frame; only the temporal terms
couple frames: a frame with its neighbours and, through the acceleration, with the frames two
apart), are assembled with batched numpy products (no Python loops over
frames or joints) and solved with ``scipy.linalg.solveh_banded``. A step is accepted only if it
lowers the true robust energy, so ``energy_history`` never increases. The per-frame terms are
evaluated in chunks of frames, on ``threads`` threads if asked (the same result bit for bit).

**Hand model** (``hand_model=True``; this function's default is off, a session's
``settings.hand_model`` is on): the velocity term's weight (itself off by
default) of each frame pair is divided by ``1 + (v / temporal_motion_mm)²`` (``v`` the pair's
median joint displacement in the initialization), and after the solve a frame whose hand-model
energy (:func:`handanno_core.handmodel.frame_energy`, fitted to its own crop) rose to more than 3x
(``RefineWeights.model_keep_ratio``) keeps its initialization: refinement may not throw a frame
off its own depth, but may move a hidden finger the model cannot see. The model
energy is also a term of the LM (``RefineWeights.model`` > 0: θ-space blocks added to the
diagonal of the banded system). Last (``recover=True``), the frames the model still cannot explain
are fitted again from their well-explained neighbours and per-finger hypotheses
(:mod:`handanno_core.recover`; ``RefineResult.info["recovered"]``).

Versus the anchors (anchor-algorithms.md §d): weights are √λ in mm/px instead of λ/N; the
appearance template is the closest *true* reference; smoothing is in camera coordinates along
true time order, robust, cut at sequence breaks; bones are exact instead of a quadratic penalty;
depth bounds exist for every frame; memory is O(N·J) besides the crops (no N×J×128×128 maps).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from functools import partial
from typing import NamedTuple

import numpy as np

from . import handmodel as hmod
from .annotation import FrameAnnotation
from .camera import CameraIntrinsics
from .crops import DEFAULT_CROP, image_to_crop
from .handmodel import Kinematics as _Kinematics
from .handmodel import angle_jacobian, angle_violation
from .hands import BoneTable, bone_table
from .lm import Nielsen, NormalEquations, levenberg_marquardt, solve_banded
from .memory import reuse_freed_memory
from .sampling import bilinear_gradient
from .skeleton import Skeleton

__all__ = ["RefineResult", "RefineWeights", "refine"]


@dataclass(frozen=True)
class RefineWeights:
    """Weights λ of the refinement energy; each residual is multiplied by √λ in the stated unit.

    Defaults were chosen on the project's synthetic data (``synth.generate_sequence`` seed 0,
    MSRA-21, 220 mm / 128 px crops centred by ``crops.locate_hands``, exact simulated 2D on the
    references) with two initializations: the real propagation (``propagate.propagate`` from a
    5 % / 2 % ``forest`` selection, reference poses = ground truth to skip the lift) and perturbed
    ground truth (smooth 5-10 mm offsets correlated in time, larger at fingertips, 2 % outlier
    frames of 20-40 mm, bone violations); chosen by ``benchmarks/bench_refine.py``, figures in
    ``benchmarks/results/design_measurements.md``.

    * ``appearance`` (per mm² per patch sample; 7×7 samples, 2 crop px apart, per joint): 0.02,
      so one joint's patch weighs about 1/mm², like the temporal term. Samples are robust with
      a redescending Welsch loss of scale ``appearance_scale_mm`` = 10 mm (Huber made silhouette
      mismatches pull joints tens of mm away); relative depths are clipped at ±40 mm so background
      is a constant. Only joints visible in the closest reference use it (an occluded joint's
      patch shows its occluder).
    * ``acceleration`` (per mm² per joint and triple of consecutive frames): 1.0, Huber scale
      ``acceleration_huber_mm`` = 2 mm (15 before stop 44): quadratic over the propagation's
      jitter, linear beyond, so a hand that turns sharply within a few frames (recorded motion
      does, between long steady stretches) pays per mm, not per mm², and is not rounded off;
      chosen on the suite's tune part (README). A constant-velocity prior: it removes the
      frame-to-frame jitter of the propagation without pulling a moving hand towards a standing
      one. It replaced the velocity term
      ``temporal`` (1.0 before), which on real fast motion dragged every frame between two
      references towards their average pose and made refinement worse than its initialization;
      chosen on the benchmark suite's tune part (``benchmarks/bench_refine_temporal.py``, figures
      in ``benchmarks/results/refine_temporal_tune.json`` and the README). The weight is
      multiplied per solve by :func:`acceleration_factor`: ``(acceleration_scale_mm / a)²``
      (2 mm per frame²), within ``acceleration_factor_range`` (0.25-64), ``a`` the hand's own
      median joint acceleration estimated from the initialization
      (:func:`signal_acceleration`), so a hand that turns sharply is smoothed less and one that
      moves steadily, fast or slow, more. It replaced (stop 38) a law on the initialization's
      median speed, which could not tell a fast sharply turning fist from fast steady motion;
      chosen on the suite's tune part (README); ``acceleration_scale_mm=None``: the constant
      weight.
    * ``temporal`` (per mm² per joint and consecutive-frame pair, Huber ``temporal_huber_mm``):
      0, the velocity prior, kept for comparison.
    * ``reprojection`` (per px² on the references' annotated 2D): 20, used when the references
      are refined too (``refine(hold_references=False)``); anchors them to a fraction of a pixel
      with exact annotations; lower it (to about 1/σ² for σ px of annotation noise) for noisy
      annotators.
    * ``depth_band`` (per mm² outside Eq. 3's band ``[D + offset, D + offset + eps_mm]``): 1.0 with
      a Welsch loss of scale 10 mm: a joint whose projection falls on a far surface (a fingertip
      just off the finger, onto the palm behind it) is not dragged there (a plain or Huber
      penalty pushed such tips 60-90 mm back).
    * ``angle`` (per degree² outside ``skeleton.angle_limits``): 0.01, a soft guard (the synthetic
      ground truth itself exceeds ``Skeleton.joint_angles`` limits at some DIP joints, so more
      is harmful).
    * ``init`` (per mm² to the initialization, Huber 10 mm): 0.03. Without it joints with little
      data (occluded, fingertips) drift with their neighbours; higher weights kept too much of the
      propagation error.
    """

    appearance: float = 0.02
    appearance_scale_mm: float = 10.0
    appearance_clip_mm: float = 40.0
    appearance_visible_only: bool = True
    acceleration: float = 1.0
    acceleration_huber_mm: float = 2.0
    acceleration_scale_mm: float | None = 2.0
    acceleration_factor_range: tuple[float, float] = (0.25, 64.0)
    temporal: float = 0.0
    temporal_huber_mm: float = 15.0
    reprojection: float = 20.0
    depth_band: float = 1.0
    depth_band_scale_mm: float = 10.0
    eps_mm: float = 15.0
    angle: float = 0.01
    init: float = 0.03
    init_huber_mm: float = 10.0
    patch_size: int = 7
    patch_spacing_px: float = 2.0
    #: with the model on, multiplies the hand-model energy of each frame (handmodel.frame_energy)
    #: inside the LM (0: the model only in propagation and the never-worse check); 3 chosen on the
    #: suite's tune part over 0, 1, 3 (and 0, 0.3, 1, 3 with the earlier keep check;
    #: ``benchmarks/bench_refine_model.py``, figures in the README)
    model: float = 3.0
    #: with the model on, the temporal weight of a frame pair is divided by 1 + (v / this)², v the
    #: pair's median joint displacement in the initialization (mm/frame): fast motion is not
    #: smoothed away
    temporal_motion_mm: float = 8.0
    #: with the model on, a frame keeps its initialization when refinement raised its model
    #: energy by more than this fraction (and by more than 1). 2 (the energy tripled): 0.1 kept
    #: ~95 % of the frames, including wrong model fits that refinement would have corrected (the
    #: model energy cannot see a hidden finger); chosen on the suite's tune part (README)
    model_keep_ratio: float = 2.0


@dataclass
class RefineResult:
    """Output of :func:`refine`.

    ``joints_mm`` (N, J, 3) refined joints in mm; ``energy_history`` total energy before the first
    and after every iteration (non-increasing); ``bone_violation_max_mm`` max |‖bone‖ − L| over all
    frames and bones; ``terms`` final energy per term; ``iterations`` LM iterations run.
    """

    joints_mm: np.ndarray
    energy_history: list[float]
    bone_violation_max_mm: float
    terms: dict[str, float]
    iterations: int = 0
    converged: bool = False
    time_s: float = 0.0
    info: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------------------
# robust helpers
# ------------------------------------------------------------------------------------------------
def _huber(r_abs: np.ndarray, delta: float) -> tuple[np.ndarray, np.ndarray]:
    """Huber cost ρ(r) (½r² inside) and IRLS weight ψ(r)/r for absolute residuals."""
    inside = r_abs <= delta
    cost = np.where(inside, 0.5 * r_abs**2, delta * (r_abs - 0.5 * delta))
    weight = np.where(inside, 1.0, delta / np.maximum(r_abs, 1e-12))
    return cost, weight


def _welsch(r_abs: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Welsch (redescending) cost ``(c²/2)(1 − exp(−(r/c)²))`` and its IRLS weight ``exp(−(r/c)²)``.

    ≈ ½r² for small r; violations much larger than ``scale`` stop pulling (they are taken as the
    joint projecting onto a different surface, e.g. the palm behind a fingertip).
    """
    e = np.exp(-((r_abs / scale) ** 2))
    return 0.5 * scale**2 * (1.0 - e), e


def _sample_crops(crops: np.ndarray, frame: np.ndarray, x: np.ndarray, y: np.ndarray, size: int):
    """Crop values at crop px (x, y) of ``crops[frame]`` with their gradient (float32), and a
    foreground flag: all four neighbours inside the crop and strictly inside (-1, 1), i.e. real
    depth. Outside the crop the value is +1 (background) with zero gradient."""
    s = bilinear_gradient(crops, x, y, frame=frame, dtype=np.float32)
    inside = (x >= 0) & (x <= size - 1) & (y >= 0) & (y <= size - 1)
    fg = inside & (s.hi < 0.999) & (s.lo > -0.999)
    val = np.where(inside, s.value, np.float32(1.0))
    gx = np.where(inside, s.dx, np.float32(0.0))
    gy = np.where(inside, s.dy, np.float32(0.0))
    return val, gx, gy, fg


# ------------------------------------------------------------------------------------------------
# the problem
# ------------------------------------------------------------------------------------------------
class _ModelRows(NamedTuple):
    """The hand model's part of an evaluation: ``chunks`` ``[(frames, rows)]``, the residual rows
    of every chunk of frames (:func:`handmodel.frame_energy_rows`), and ``energy`` ``(N,)`` each
    frame's model energy (unweighted)."""

    chunks: list
    energy: np.ndarray


@dataclass
class _Evaluation:
    """The energy at poses ``(root (N, 6), u (N, P-6))`` and its X-space normal-equation pieces.

    ``terms``: energy per term; ``x``: joints (N, J, 3) mm; ``hd`` (N, J, 3, 3) / ``gx`` (N, J, 3):
    per-joint Hessian blocks and gradient of the per-frame terms; ``wt`` (N-1, J) / ``wa``
    (N-2, J): IRLS weights of the velocity / acceleration terms (None without the term); ``ang``: ``(frames, violations)`` of the frames
    outside their angle limits (None if none; their θ-Jacobian is taken in the normal equations
    only, not at trial points the LM rejects); ``mod``: the hand model's :class:`_ModelRows`
    (made into θ-space blocks in the normal equations only, like the angles; None if off)."""

    root: np.ndarray
    u: np.ndarray
    terms: dict[str, float]
    x: np.ndarray
    hd: np.ndarray
    gx: np.ndarray
    wt: np.ndarray | None
    wa: np.ndarray | None
    ang: tuple | None
    mod: _ModelRows | None

    @property
    def cost(self) -> float:
        return sum(self.terms.values())


def signal_acceleration(init_mm: np.ndarray, pair_ok: np.ndarray) -> float | None:
    """The hand's own median joint acceleration (mm per frame²) in ``init_mm`` (N, J, 3) mm,
    over consecutive frames that do not cross a break (``pair_ok`` (N-1,) bool); None with
    nothing to measure.

    The initialization is the hand's motion plus the propagation's frame-to-frame jitter. Jitter
    independent from frame to frame with spread σ has a second difference of variance 6σ² and a
    third of 20σ²; the hand's motion is smooth, its third difference small against its second.
    So the jitter's part of the median acceleration ``A`` is ``√(6/20)`` times the median third
    difference ``D``, and the hand's own is what remains: ``√(max(A² − 0.3 D², 0))``."""
    x = np.asarray(init_mm, dtype=np.float64)
    ok = np.asarray(pair_ok, dtype=bool)
    ok3 = ok[:-1] & ok[1:]
    ok4 = ok3[:-1] & ok3[1:]
    if len(x) < 4 or not ok4.any():
        return None
    second = np.diff(x, 2, axis=0)
    acc = np.linalg.norm(second, axis=-1)[ok3]
    third = np.linalg.norm(np.diff(second, axis=0), axis=-1)[ok4]
    acc, third = acc[np.isfinite(acc)], third[np.isfinite(third)]
    if not (len(acc) and len(third)):
        return None
    a, d = float(np.median(acc)), float(np.median(third))
    return float(np.sqrt(max(a * a - 0.3 * d * d, 0.0)))


def acceleration_factor(init_mm: np.ndarray, pair_ok: np.ndarray, w: RefineWeights) -> float:
    """The factor on ``w.acceleration`` for a sequence whose initialization ``init_mm`` (N, J, 3)
    mm shows the hand accelerating its joints by a median of ``a`` mm per frame²
    (:func:`signal_acceleration`; consecutive pairs ``pair_ok`` (N-1,) bool, not across a
    break): ``(w.acceleration_scale_mm / a)²`` within ``w.acceleration_factor_range``; 1 with
    ``acceleration_scale_mm`` None or nothing to measure.

    A constant-velocity prior's spread should be the hand's own acceleration: one weight
    over-smoothed sharply turning motion and under-smoothed steady motion, and the speed alone
    cannot tell them apart (two sequences moving as fast can turn unequally sharply; README,
    stop 38)."""
    if w.acceleration_scale_mm is None:
        return 1.0
    a = signal_acceleration(init_mm, pair_ok)
    if a is None:
        return 1.0
    lo, hi = w.acceleration_factor_range
    return float(np.clip((w.acceleration_scale_mm / max(a, 1e-3)) ** 2, lo, hi))


class _Problem:
    def __init__(
        self,
        init_mm,
        crops,
        boxes,
        centres_mm,
        camera: CameraIntrinsics,
        skeleton: Skeleton,
        kin: _Kinematics,
        reference_frames,
        reference_annotations,
        closest_reference,
        sequence_breaks,
        weights: RefineWeights,
        cube_mm: float,
        chunk: int,
    ):
        self.w = weights
        self.cam = camera
        self.skel = skeleton
        self.kin = kin
        self.init = init_mm
        n, j = init_mm.shape[:2]
        self.n, self.j = n, j
        self.chunk = chunk
        self.size = int(crops.shape[-1])
        self.crops = np.asarray(crops)  # (N, S, S); a memmap stays on disk
        self.boxes = np.asarray(boxes, dtype=np.float64)
        self.zc = np.asarray(centres_mm, dtype=np.float64)[:, 2]
        self.half = 0.5 * cube_mm
        self.offsets = np.asarray(skeleton.surface_offsets_mm, dtype=np.float64)
        g = weights.patch_size
        o = (np.arange(g) - (g - 1) / 2) * weights.patch_spacing_px
        gy, gx = np.meshgrid(o, o, indexing="ij")
        self.grid = np.stack([gx.ravel(), gy.ravel()], axis=-1)  # (G,2)

        # temporal pairs (i, i+1) not crossing a break
        pair_ok = np.ones(max(n - 1, 0), dtype=bool)
        for b in sequence_breaks:
            if 0 < b < n:
                pair_ok[b - 1] = False
        self.pair_ok = pair_ok
        self.acceleration = weights.acceleration * acceleration_factor(init_mm, pair_ok, weights)

        # references: projection targets and appearance templates
        refs = np.asarray(sorted(set(int(r) for r in reference_frames)), dtype=np.int64)
        self.refs = refs
        self.ref_uv = np.full((len(refs), j, 2), np.nan)
        self.ref_visible = np.ones((len(refs), j), dtype=bool)
        for a, r in enumerate(refs):
            ann: FrameAnnotation | None = reference_annotations.get(int(r))
            if ann is None:
                continue
            self.ref_uv[a] = np.asarray(ann.uv_px, dtype=np.float64)
            self.ref_visible[a] = np.asarray(ann.visible, dtype=bool)
        self.ref_has = np.all(np.isfinite(self.ref_uv), axis=-1)
        pos = np.full(n, -1, dtype=np.int64)
        pos[refs] = np.arange(len(refs))
        cr = np.asarray(closest_reference, dtype=np.int64)
        if cr.shape != (n,):
            raise ValueError(f"closest_reference must be ({n},), got {cr.shape}")
        self.tmpl_of = np.where((cr >= 0) & (cr < n), pos[np.clip(cr, 0, n - 1)], -1)
        self.visible = np.where(
            self.tmpl_of[:, None] >= 0, self.ref_visible[np.maximum(self.tmpl_of, 0)], True
        )
        self.templates, self.tmpl_valid = self._templates()
        # hand model (set by refine() when switched on)
        self.model: hmod.HandModel | None = None
        self.obs: hmod.FrameObservations | None = None
        self.fit_w = hmod.FitWeights()
        self.model_chunk = 32
        self.pair_scale = np.ones(max(n - 1, 0))
        self.pool: ThreadPoolExecutor | None = None  #: set by refine() with threads > 1

    def map_chunks(self, fn: Callable, n: int, chunk: int) -> list:
        """``[fn(frames) for frames in chunks of range(n)]`` in order, on the thread pool if there
        is one (numpy releases the GIL in its array loops; each chunk writes only its own rows, and
        the caller sums the results in chunk order, so threads change no bit of the result)."""
        return self.map_items(fn, [np.arange(a, min(n, a + chunk)) for a in range(0, n, chunk)])

    def map_items(self, fn: Callable, items: list) -> list:
        """``[fn(item) for item in items]`` in order, on the thread pool if there is one."""
        if self.pool is None or len(items) < 2:
            return [fn(item) for item in items]
        return list(self.pool.map(fn, items))

    # -------------------------------------------------------------------- geometry
    def _crop_xy(self, x: np.ndarray, frames: np.ndarray):
        """joints (n,J,3) -> crop px (n,J,2) and d(crop px)/dX (n,J,2,3)."""
        b = self.boxes[frames][:, None]
        uv = self.cam.project(x)
        pj = self.cam.projection_jacobian(x)
        jac = pj / b[..., 2:4, None]
        return image_to_crop(uv, b), jac, uv, pj

    def _templates(self):
        """Reference patches (K,J,G) in mm relative to the reference joint's depth."""
        k = len(self.refs)
        j, gsz = self.j, len(self.grid)
        out = np.zeros((k, j, gsz), np.float32)
        valid = np.zeros((k, j), dtype=bool)
        if k == 0:
            return out, valid
        x = self.init[self.refs]
        xy, _, uv, _ = self._crop_xy(x, self.refs)
        ann_xy = image_to_crop(self.ref_uv, self.boxes[self.refs][:, None])
        xy = np.where(self.ref_has[..., None], ann_xy, xy)
        px = xy[..., None, 0] + self.grid[:, 0]
        py = xy[..., None, 1] + self.grid[:, 1]
        val, _, _, _ = _sample_crops(self.crops, self.refs[:, None, None], px, py, self.size)
        rel = self.zc[self.refs][:, None, None] + self.half * val - x[..., 2:3]
        clip = self.w.appearance_clip_mm
        out[:] = np.clip(rel, -clip, clip)
        valid[:] = np.all(np.isfinite(xy), axis=-1) & np.all(np.isfinite(x), axis=-1)
        return out, valid

    # -------------------------------------------------------------------- evaluation
    def evaluate(self, root, u) -> _Evaluation:
        """Energy terms at (root, u) and the X-space normal-equation pieces."""
        n, j = self.n, self.j
        x = self.kin.joints(root, u)
        terms = dict.fromkeys(
            (
                "appearance",
                "acceleration",
                "temporal",
                "reprojection",
                "depth_band",
                "angle",
                "init",
            ),
            0.0,
        )
        hd = np.zeros((n, j, 3, 3))
        gx = np.zeros((n, j, 3))
        # per-frame terms, chunked over frames (memory ~ chunk·J·G)

        def per_frame(fr):
            xy, dxy, _, _ = self._crop_xy(x[fr], fr)
            band = self._depth_band(x[fr], fr, xy, hd, gx)
            return band, self._appearance(x[fr], fr, xy, dxy, hd, gx)

        for band, app in self.map_chunks(per_frame, n, self.chunk):
            terms["depth_band"] += band
            terms["appearance"] += app
        mod = self._model_blocks(root, u, terms)
        terms["reprojection"] = self._reprojection(x, hd, gx)
        terms["init"] = self._init_prior(x, hd, gx)
        terms["temporal"], wt = self._temporal(x, hd, gx)
        terms["acceleration"], wa = self._acceleration(x, hd, gx)
        terms["angle"], ang = self._angles(x)
        return _Evaluation(root, u, terms, x, hd, gx, wt, wa, ang, mod)

    def _depth_band(self, xc, fr, xy, hd, gx) -> float:
        """Depth band of frames ``fr`` (observed depth D from the crop at the joint's projection,
        treated as constant: the residual depends on Z only); adds to ``hd``/``gx``."""
        w = self.w
        val, _, _, fg = _sample_crops(self.crops, fr[:, None], xy[..., 0], xy[..., 1], self.size)
        lo = self.zc[fr][:, None] + self.half * val + self.offsets
        z = xc[..., 2]
        below = np.where(fg, np.maximum(lo - z, 0.0), 0.0)
        above = np.where(fg & self.visible[fr], np.maximum(z - (lo + w.eps_mm), 0.0), 0.0)
        cost_below, w_below = _welsch(below, w.depth_band_scale_mm)
        cost_above, w_above = _welsch(above, w.depth_band_scale_mm)
        hd[fr, :, 2, 2] += w.depth_band * (w_below * (below > 0) + w_above * (above > 0))
        gx[fr, :, 2] += w.depth_band * (-w_below * below + w_above * above)
        return w.depth_band * float(np.sum(cost_below) + np.sum(cost_above))

    def _appearance(self, xc, fr, xy, dxy, hd, gx) -> float:
        """Appearance of frames ``fr`` against their reference's template patches."""
        w = self.w
        clip = w.appearance_clip_mm
        tpos = self.tmpl_of[fr]
        has_t = (tpos >= 0)[:, None] & self.tmpl_valid[np.maximum(tpos, 0)]
        if w.appearance_visible_only:
            has_t &= self.visible[fr]
        if not (w.appearance > 0 and np.any(has_t)):
            return 0.0
        px = xy[..., None, 0] + self.grid[:, 0]
        py = xy[..., None, 1] + self.grid[:, 1]
        v, vx, vy, _ = _sample_crops(self.crops, fr[:, None, None], px, py, self.size)
        zc = self.zc[fr][:, None]
        rel = (zc - xc[..., 2]).astype(np.float32)[..., None] + np.float32(self.half) * v
        inside = np.abs(rel) < clip
        rel = np.clip(rel, -clip, clip)
        tm = self.templates[np.maximum(tpos, 0)]
        r = np.where(has_t[..., None], rel - tm, 0.0)
        cost, wr = _welsch(np.abs(r), w.appearance_scale_mm)
        # dr/dX = half·∇c·d(xy)/dX − e_z, zero where the relative depth is clipped
        gxy = np.float32(self.half) * np.stack([vx, vy], axis=-1)  # (n,J,G,2)
        ja = np.matmul(gxy, dxy.astype(np.float32))  # (n,J,G,3)
        ja[..., 2] -= 1.0
        ja *= inside[..., None]
        ww = (w.appearance * wr * has_t[..., None]).astype(np.float32)
        jw = (ja * ww[..., None]).swapaxes(-1, -2)  # (n,J,3,G)
        hd[fr] += np.matmul(jw, ja)
        gx[fr] += np.matmul(jw, r[..., None])[..., 0]
        return w.appearance * float(np.sum(cost, dtype=np.float64))

    def _model_blocks(self, root, u, terms: dict[str, float]):
        """Hand model fitted to each frame's own depth: its :class:`_ModelRows` (their θ-space
        blocks are made by :meth:`_model_normal_equations` for the evaluations the LM keeps;
        None when off); sets ``terms["model"]``."""
        w = self.w
        if self.model is None or w.model <= 0:
            return None
        terms["model"] = 0.0
        energy = np.zeros(self.n)

        def rows(fr):
            obs = self.obs.take(slice(fr[0], fr[-1] + 1))  # a view: chunks are ranges
            e, r = hmod.frame_energy_rows(
                self.model, self.kin, root[fr], u[fr], obs, self.cam, self.fit_w
            )
            return fr, e, r

        chunks = []
        for fr, e, r in self.map_chunks(rows, self.n, self.model_chunk):
            terms["model"] += w.model * float(np.sum(e))
            energy[fr] = e
            chunks.append((fr, r))
        return _ModelRows(chunks, energy)

    def _model_normal_equations(self, ev: _Evaluation) -> tuple[np.ndarray, np.ndarray]:
        """θ-space hand-model blocks ``((N,P,P), (N,P))`` (weighted) of ``ev``'s rows."""
        p = self.kin.num_params
        h_all, g_all = np.empty((self.n, p, p)), np.empty((self.n, p))

        def blocks(chunk):
            fr, r = chunk
            h, g = hmod.rows_normal_equations(
                self.model, self.kin, ev.root[fr], ev.u[fr], self.fit_w, r
            )
            h_all[fr] = self.w.model * h
            g_all[fr] = self.w.model * g

        self.map_items(blocks, ev.mod.chunks)
        return h_all, g_all

    def _reprojection(self, x, hd, gx) -> float:
        """Reprojection on the reference frames' annotated 2D."""
        if not len(self.refs):
            return 0.0
        w = self.w
        xr = x[self.refs]
        res = np.where(self.ref_has[..., None], self.cam.project(xr) - self.ref_uv, 0.0)
        pj = self.cam.projection_jacobian(xr) * self.ref_has[..., None, None]
        hd[self.refs] += w.reprojection * np.einsum("nkac,nkad->nkcd", pj, pj)
        gx[self.refs] += w.reprojection * np.einsum("nkac,nka->nkc", pj, res)
        return w.reprojection * 0.5 * float(np.sum(res**2))

    def _init_prior(self, x, hd, gx) -> float:
        """Optional Huber prior to the initialization."""
        w = self.w
        if w.init <= 0:
            return 0.0
        dvec = x - self.init
        cost, wi = _huber(np.linalg.norm(dvec, axis=-1), w.init_huber_mm)
        hd += (w.init * wi)[..., None, None] * np.eye(3)
        gx += (w.init * wi)[..., None] * dvec
        return w.init * float(np.sum(cost))

    def _temporal(self, x, hd, gx) -> tuple[float, np.ndarray | None]:
        """Temporal smoothness (Huber on the per-joint displacement); its IRLS weights (N-1, J)."""
        w = self.w
        if self.n <= 1 or w.temporal <= 0:
            return 0.0, None
        dvec = x[1:] - x[:-1]
        cost, wt = _huber(np.linalg.norm(dvec, axis=-1), w.temporal_huber_mm)
        scale = (self.pair_ok * self.pair_scale)[:, None]
        wt = w.temporal * wt * scale
        eye = np.eye(3)
        hd[:-1] += wt[..., None, None] * eye
        hd[1:] += wt[..., None, None] * eye
        gx[:-1] -= wt[..., None] * dvec
        gx[1:] += wt[..., None] * dvec
        return w.temporal * float(np.sum(cost * scale)), wt

    def _acceleration(self, x, hd, gx) -> tuple[float, np.ndarray | None]:
        """Constant-velocity prior (Huber on the per-joint second difference, not across a break);
        its IRLS weights (N-2, J)."""
        w = self.w
        lam = self.acceleration
        if self.n <= 2 or lam <= 0:
            return 0.0, None
        acc = x[2:] - 2.0 * x[1:-1] + x[:-2]
        cost, wa = _huber(np.linalg.norm(acc, axis=-1), w.acceleration_huber_mm)
        scale = (self.pair_ok[:-1] & self.pair_ok[1:]).astype(np.float64)[:, None]
        wa = lam * wa * scale
        eye = np.eye(3)
        hd[:-2] += wa[..., None, None] * eye
        hd[1:-1] += 4.0 * wa[..., None, None] * eye
        hd[2:] += wa[..., None, None] * eye
        gx[:-2] += wa[..., None] * acc
        gx[1:-1] -= 2.0 * wa[..., None] * acc
        gx[2:] += wa[..., None] * acc
        return lam * float(np.sum(cost * scale)), wa

    def _angles(self, x) -> tuple[float, tuple | None]:
        """Joint-angle limits: energy and ``(frames, violations)`` of the frames outside them
        (None if none)."""
        w = self.w
        if w.angle <= 0 or self.skel.flexion_limits_deg is None:
            return 0.0, None
        viol = self._angle_violation(x)
        active = np.flatnonzero(np.any(viol > 0, axis=1))
        ang = (active, viol[active]) if len(active) else None
        return w.angle * 0.5 * float(np.sum(viol**2)), ang

    def _angle_violation(self, x: np.ndarray) -> np.ndarray:
        """(n, 2A) degrees outside the flexion/abduction limits (0 inside)."""
        return angle_violation(self.skel, x)

    def _angle_jacobian(self, root: np.ndarray, u: np.ndarray, v0: np.ndarray):
        """d(violation)/dθ (m,2A,P) at violations ``v0`` (m,2A) (forward differences, see
        handmodel), in chunks of frames that perturb the bones of all of them."""
        bones = hmod.violated_bones(self.skel, v0)

        def chunk(fr):
            return angle_jacobian(self.skel, self.kin, root[fr], u[fr], v0=v0[fr], bones=bones)[1]

        return np.concatenate(self.map_chunks(chunk, len(v0), 256))


# ------------------------------------------------------------------------------------------------
# block-tridiagonal system in θ-space
# ------------------------------------------------------------------------------------------------
def _solve_fixed(system: NormalEquations, lam: float, frozen: np.ndarray) -> np.ndarray:
    """Banded damped step with the parameters of fixed frames (``frozen`` (N·P,) bool) at 0."""
    step = solve_banded(system, lam)
    step[frozen] = 0.0
    return step


#: frames per chunk of :func:`_assemble`: the kinematic Jacobian and its products of a chunk stay
#: in cache (one pass over all frames at once is memory-bound) and chunks run on the thread pool
ASSEMBLE_CHUNK = 64


def _assemble(problem: _Problem, ev: _Evaluation, fixed: np.ndarray):
    """θ-space diagonal blocks (N,P,P), first and second super-diagonal blocks (N-1,P,P) and
    (N-2,P,P) (None without the acceleration term) and gradient (N,P) from the X-space pieces of
    ``ev`` and the kinematic Jacobian dX/dθ (taken per chunk of :data:`ASSEMBLE_CHUNK` frames,
    with the two frames after it that the off-diagonal blocks pair with)."""
    hd, gx, wt, ang, mod = ev.hd, ev.gx, ev.wt, ev.ang, ev.mod
    n, j = problem.n, problem.j
    kin = problem.kin
    p = kin.num_params
    diag = np.empty((n, p, p))
    grad = np.empty((n, p))
    off = np.zeros((max(n - 1, 0), p, p))
    off2 = np.empty((max(n - 2, 0), p, p)) if ev.wa is not None else None
    c = None
    if ev.wa is not None:
        # residual X[i-1] - 2X[i] + X[i+1]: pairs (k, k+1) get -2w from the triples centred at k
        # and at k+1, frames two apart get +w
        c = np.zeros((max(n - 1, 0), j))
        c[1:] -= 2.0 * ev.wa
        c[:-1] -= 2.0 * ev.wa

    def chunk(fr):
        a, b = int(fr[0]), int(fr[-1]) + 1
        m = kin.jacobian(ev.u[a : min(b + 2, n)])  # (h, 3J, P), local frame i - a
        own = m[: b - a]
        hm = np.matmul(hd[a:b], own.reshape(b - a, j, 3, p))
        diag[a:b] = np.matmul(own.transpose(0, 2, 1), hm.reshape(b - a, j * 3, p))
        grad[a:b] = np.einsum("nrp,nr->np", own, gx[a:b].reshape(b - a, j * 3))
        e1 = min(b, n - 1)  # pairs (i, i+1) for i in a..e1-1
        if e1 > a:
            k = e1 - a
            if wt is not None:
                wrep = np.repeat(wt[a:e1], 3, axis=1)
                off[a:e1] = -np.matmul((m[:k] * wrep[..., None]).transpose(0, 2, 1), m[1 : k + 1])
            if c is not None:
                crep = np.repeat(c[a:e1], 3, axis=1)[..., None]
                off[a:e1] += np.matmul((m[:k] * crep).transpose(0, 2, 1), m[1 : k + 1])
        e2 = min(b, n - 2)
        if off2 is not None and e2 > a:
            k = e2 - a
            w2 = np.repeat(ev.wa[a:e2], 3, axis=1)[..., None]
            off2[a:e2] = np.matmul((m[:k] * w2).transpose(0, 2, 1), m[2 : k + 2])

    problem.map_chunks(chunk, n, ASSEMBLE_CHUNK)
    if ang is not None:
        frames, v0 = ang
        jm = problem._angle_jacobian(ev.root[frames], ev.u[frames], v0)  # (a, 2A, P) in θ
        wa = problem.w.angle
        diag[frames] += wa * np.matmul(jm.transpose(0, 2, 1), jm)
        grad[frames] += wa * np.einsum("arp,ar->ap", jm, v0)
    if mod is not None:
        h_model, g_model = problem._model_normal_equations(ev)
        diag += h_model
        grad += g_model
    if np.any(fixed):
        diag[fixed] = np.eye(p)
        grad[fixed] = 0.0
        off[fixed[:-1]] = 0.0
        off[fixed[1:]] = 0.0
        if off2 is not None:
            off2[fixed[:-2]] = 0.0
            off2[fixed[2:]] = 0.0
    return diag, off, off2, grad


def _banded(diag: np.ndarray, off: np.ndarray, off2: np.ndarray | None = None) -> np.ndarray:
    """Upper banded storage (u+1, N·P) of the symmetric block-banded matrix with diagonal blocks
    ``diag`` (N,P,P), first super-diagonal blocks ``off`` (N-1,P,P) and, if given, second
    super-diagonal blocks ``off2`` (N-2,P,P); u = 2P-1 without ``off2``, 3P-1 with it.

    ``ab[u + r - c, c] = A[r, c]`` for r <= c, in Fortran order (the layout LAPACK reads; a
    C-ordered band is transposed on every solve). Column ``c = iP + k`` of the band is column
    ``k`` of block column ``i`` (the blocks above the diagonal stacked, ``off2[i-2]``,
    ``off[i-1]``, ``diag[i]``) from its row ``k + 1 - P`` on: one sheared view of the block
    columns, copied once.
    """
    n, p = diag.shape[:2]
    second = off2 is not None and n > 2
    width = 3 * p if second else 2 * p  # u + 1
    # columns[i, k, P + q] = A[block i - (width/P - 1), row q; block i, column k]; P zeros in
    # front stand for the rows above the band
    columns = np.empty((n, p, p + width))  # every entry the view reads is written below
    columns[:, :, :p] = 0.0
    columns[:, :, width:] = diag.transpose(0, 2, 1)
    columns[:1, :, width - p : width] = 0.0
    if n > 1:
        columns[1:, :, width - p : width] = off.transpose(0, 2, 1)
    if second:
        columns[:2, :, p : 2 * p] = 0.0
        columns[2:, :, p : 2 * p] = off2.transpose(0, 2, 1)
    s0, s1, s2 = columns.strides
    sheared = np.lib.stride_tricks.as_strided(
        columns[:, :, 1:], shape=(n, p, width), strides=(s0, s1 + s2, s2), writeable=False
    )  # sheared[i, k, t] = columns[i, k, k + 1 + t]
    return np.ascontiguousarray(sheared).reshape(n * p, width).T


def _use_model(problem: _Problem, hand_model, fit_weights, init, crops, boxes, centres, cube_mm):
    """Switch the hand-model term on: observations of every frame, the personalized model and the
    motion-adaptive temporal weights."""
    refs = problem.refs[np.all(np.isfinite(init[problem.refs]), axis=(1, 2))]
    # the refinement has its own angle prior; the model term brings data, free space, collisions,
    # the palm shape and the session's pose prior
    fit_w = replace(fit_weights or hmod.FitWeights(), angle=0.0, pose=0.0, uv=0.0)

    def observe(frames, points=fit_w.points, out=None):
        return hmod.observe(
            crops[frames], np.asarray(boxes)[frames], np.asarray(centres)[frames], problem.cam,
            cube_mm=cube_mm, max_points=points, out=out,
            planes=hmod.wrist_planes(problem.skel, init[frames]),
        )  # fmt: skip

    # every chunk written into the sequence's arrays (no second copy of all frames)
    obs = hmod.FrameObservations.allocate(problem.n, crops.shape[-1], fit_w.points)
    problem.map_chunks(
        lambda fr: observe(slice(fr[0], fr[-1] + 1), out=obs.take(slice(fr[0], fr[-1] + 1))),
        problem.n, 128,
    )  # fmt: skip
    if isinstance(hand_model, hmod.HandModel):
        model = hand_model
    elif len(refs):
        same = fit_w.points == hmod.OBSERVED_POINTS  # else the references observed as always
        ref_obs = obs.take(refs) if same else observe(refs, hmod.OBSERVED_POINTS)
        model = hmod.personalize(problem.skel, problem.kin.lengths, init[refs], ref_obs)
    else:
        return
    problem.model, problem.obs, problem.fit_w = model, obs, fit_w
    if problem.n > 1 and problem.w.temporal_motion_mm > 0:
        v = np.median(np.linalg.norm(np.diff(init, axis=0), axis=-1), axis=1)
        problem.pair_scale = 1.0 / (1.0 + (v / problem.w.temporal_motion_mm) ** 2)


def _model_energy(problem: _Problem, root, u) -> np.ndarray:
    """(N,) hand-model energy of every frame at (root, u)."""

    def energy(fr):
        obs = problem.obs.take(slice(fr[0], fr[-1] + 1))  # a view: chunks are ranges
        return hmod.frame_energy(
            problem.model, problem.kin, root[fr], u[fr], obs, problem.cam, problem.fit_w,
            diagnostics=False,
        )[0]  # fmt: skip

    return np.concatenate(
        [np.zeros(0), *problem.map_chunks(energy, problem.n, 4 * problem.model_chunk)]
    )


# ------------------------------------------------------------------------------------------------
# public API
# ------------------------------------------------------------------------------------------------
def refine(
    init_mm: np.ndarray,
    *,
    crops: np.ndarray,
    boxes: np.ndarray,
    centres_mm: np.ndarray,
    camera: CameraIntrinsics,
    skeleton: Skeleton,
    bone_lengths_mm: np.ndarray,
    reference_frames: Iterable[int],
    reference_annotations: dict[int, FrameAnnotation],
    closest_reference: np.ndarray,
    sequence_breaks: Iterable[int] = (),
    weights: RefineWeights | None = None,
    iterations: int = 25,
    progress: Callable[[int, float], None] | None = None,
    fixed_frames: Iterable[int] | None = None,
    cube_mm: float = DEFAULT_CROP.cube_mm,
    tol: float = 3e-4,
    chunk_frames: int = 256,
    hand_model: bool | hmod.HandModel = False,
    fit_weights: hmod.FitWeights | None = None,
    threads: int = 1,
    hold_references: bool = True,
    recover: bool = True,
) -> RefineResult:
    """Refine all frames' joints jointly (see the module docstring for the energy).

    Parameters
    ----------
    init_mm : (N, J, 3) float mm
        Initialization (lifted references + propagated frames). Frames with NaN joints start
        from their closest reference's pose.
    crops : (N, S, S) normalized depth crops (float16 memmap is fine; not copied)
        ``(d − z_c)/(cube_mm/2)``, background +1; observed depths are read from them.
    boxes : (N, 4) crop boxes ``[u_left, v_top, sx, sy]`` (``crops.crop_boxes``).
    centres_mm : (N, 3) crop centres in mm.
    camera, skeleton : intrinsics and layout.
    bone_lengths_mm : (B,) fixed bone lengths (hard constraints), or (N, B) each frame's own
        (several people's hands, :mod:`handanno_core.hands`): the frames of each distinct set
        are then solved as their own system (:func:`_refine_by_hand`).
    reference_frames : (K,) reference frame indices; reference_annotations their 2D annotations.
    closest_reference : (N,) int, for each frame the reference frame whose crop is its
        appearance template (and whose visibility flags it uses); -1 for none.
    sequence_breaks : frames where an unrelated sequence starts (no temporal term across).
    weights : :class:`RefineWeights`.
    iterations : maximum LM iterations. ``progress(iteration, energy)`` is called after each.
    tol : the LM stops after an iteration that lowers the energy by less than this fraction of
        it (chosen on the suite's tune part over 1e-5 and 1e-3; README, stop 50).
    fixed_frames : frames kept at their initialization (returned unchanged).
    hold_references : the reference frames with a finite initialization (their lift) keep it, on
        the bone lengths (the pose's bone directions are kept). A reference is what a person
        annotated and the lift made of it; refinement moved them (tune part: references 0.64 ->
        1.53 mm on tune-icvl, 1.00 -> 1.83 on tune-shape-fast), and their neighbours lean on them
        through the temporal and appearance terms. ``False``: refined with the rest, anchored
        only by ``reprojection`` on their annotated 2D.
    hand_model : ``True`` adds the personalized hand model's energy of every frame (fitted to
        the frame's own crop; personalized from the reference frames' initialization, i.e. their
        lift), scales the temporal weight down where the initialization moves fast, and keeps a
        frame's initialization where refinement raised its model energy; a
        :class:`handmodel.HandModel` is used as given; ``False`` is the model-free energy.
    recover : with the hand model, frames it cannot explain after the solve are fitted again
        from their neighbours' estimates and per-finger hypotheses and replaced where the model
        explains them far better (:mod:`handanno_core.recover`).
    threads : threads evaluating the per-frame terms (the hand model's above all) in chunks of
        frames; the result does not depend on it (:meth:`_Problem.map_chunks`).

    Returns
    -------
    RefineResult with ``joints_mm`` (N, J, 3) mm, the non-increasing ``energy_history``,
    ``bone_violation_max_mm`` and the final energy per term in ``terms``.
    """
    t0 = time.perf_counter()
    w = weights or RefineWeights()
    sequence_breaks = [int(b) for b in sequence_breaks]
    init = np.array(init_mm, dtype=np.float64)
    if init.ndim != 3 or init.shape[2] != 3 or init.shape[1] != skeleton.num_joints:
        raise ValueError(f"init_mm must be (N, {skeleton.num_joints}, 3), got {init.shape}")
    n = init.shape[0]
    if crops.shape[0] != n or boxes.shape != (n, 4) or np.shape(centres_mm) != (n, 3):
        raise ValueError("crops, boxes and centres_mm must have one row per frame")
    closest = np.asarray(closest_reference, dtype=np.int64)
    # frames without a usable initialization start from their closest reference's pose, else from
    # the nearest initialized frame in time (e.g. references left NaN by propagation)
    finite = np.all(np.isfinite(init), axis=(1, 2))
    if not np.any(finite):
        raise ValueError("init_mm has no frame with a finite initialization")
    bad = np.flatnonzero(~finite)
    if len(bad):
        src = closest[bad]
        ok = (src >= 0) & (src < n) & finite[np.clip(src, 0, n - 1)]
        good = np.flatnonzero(finite)
        pos = np.clip(np.searchsorted(good, bad), 1, len(good)) - 1
        nxt = np.minimum(pos + 1, len(good) - 1)
        near = np.where(np.abs(good[nxt] - bad) < np.abs(good[pos] - bad), good[nxt], good[pos])
        init[bad] = init[np.where(ok, src, near)]
    fixed = np.zeros(n, dtype=bool)
    if fixed_frames is not None:
        fixed[np.asarray(list(fixed_frames), dtype=np.int64)] = True
    reference_frames = [int(r) for r in reference_frames]
    held = np.zeros(n, dtype=bool)
    if hold_references:
        refs = np.asarray(reference_frames, dtype=np.int64)
        refs = refs[(refs >= 0) & (refs < n)]
        held[refs[finite[refs]]] = True
    table = bone_table(bone_lengths_mm, n, len(skeleton.bones))
    if not table.single:
        return _refine_by_hand(
            table, init_mm, fixed, t0, crops=crops, boxes=boxes, centres_mm=centres_mm,
            camera=camera, skeleton=skeleton, reference_frames=reference_frames,
            reference_annotations=reference_annotations, closest_reference=closest,
            sequence_breaks=sequence_breaks, weights=w, iterations=iterations, progress=progress,
            cube_mm=cube_mm, tol=tol, chunk_frames=chunk_frames, hand_model=hand_model,
            fit_weights=fit_weights, threads=threads, hold_references=hold_references,
        )  # fmt: skip

    kin = _Kinematics(skeleton, table.lengths[0])
    root, u = kin.fit(init)
    flat = crops if crops.flags.c_contiguous else np.ascontiguousarray(crops)
    problem = _Problem(
        init,
        flat,
        boxes,
        centres_mm,
        camera,
        skeleton,
        kin,
        reference_frames,
        reference_annotations,
        closest,
        list(sequence_breaks),
        w,
        cube_mm,
        chunk_frames,
    )
    with _thread_pool(problem, threads), reuse_freed_memory():
        if hand_model is not False and hand_model is not None:
            _use_model(problem, hand_model, fit_weights, init, crops, boxes, centres_mm, cube_mm)
        fit, e0 = _solve(problem, root, u, fixed | held, iterations, tol, progress)
        kept = _keep_check(problem, fit, e0, (root, u), fixed | held)
    root, u = fit.x
    terms = fit.evaluation.terms
    joints = kin.joints(root, u)
    viol = float(np.max(np.abs(skeleton.bone_lengths(joints) - kin.lengths))) if n else 0.0
    joints[fixed] = np.asarray(init_mm, dtype=np.float64)[fixed]
    joints[kept] = init[kept]
    recovered = np.zeros(0, dtype=np.int64)
    if problem.model is not None and recover:
        joints, recovered = _recover(
            problem, joints, init, fixed | held, fit_weights, centres_mm, sequence_breaks
        )
    return RefineResult(
        joints_mm=joints,
        energy_history=fit.history,
        bone_violation_max_mm=viol,
        terms=terms,
        iterations=fit.iterations,
        converged=fit.converged,
        time_s=time.perf_counter() - t0,
        info={
            "lambda": fit.lam,
            "log": fit.log,
            "kept_initialization": kept.tolist(),
            "recovered": recovered.tolist(),
        },
    )


def _recover(problem: _Problem, joints: np.ndarray, init: np.ndarray, keep: np.ndarray,
             fit_weights: hmod.FitWeights | None, centres_mm: np.ndarray,
             sequence_breaks) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The refined ``joints`` (N, J, 3) mm with the frames the hand model cannot explain fitted
    again (:func:`handanno_core.recover.recover_frames`; ``keep`` (N,) bool frames unchanged);
    the references' level is that of their initialization (their lift). Returns the joints and
    the recovered frames."""
    from .recover import recover_frames

    refs = problem.refs[np.all(np.isfinite(init[problem.refs]), axis=(1, 2))]
    if len(refs) == 0:
        return joints, np.zeros(0, dtype=np.int64)
    level = hmod.reference_level(problem.model, init[refs], problem.obs.take(refs), problem.cam)
    res = recover_frames(
        problem.model, joints, problem.obs, np.asarray(centres_mm), problem.cam, level,
        keep=keep, sequence_breaks=sequence_breaks, fit_weights=fit_weights,
    )  # fmt: skip
    return res.joints_mm, res.recovered


@contextmanager
def _thread_pool(problem: _Problem, threads: int):
    """``problem.pool`` = a pool of ``threads`` threads while inside (none for ``threads`` <= 1
    or fewer than two chunks of frames)."""
    if threads <= 1 or problem.n <= problem.model_chunk:
        yield
        return
    with ThreadPoolExecutor(threads) as pool:
        problem.pool = pool
        try:
            yield
        finally:
            problem.pool = None


def _solve(problem: _Problem, root, u, fixed: np.ndarray, iterations: int, tol: float, progress):
    """The LM from (root, u) (``fixed`` frames kept); returns its result and the per-frame model
    energy at the start (None without the model term)."""
    kin, n = problem.kin, problem.n
    p = kin.num_params

    def normal_equations(_x, ev: _Evaluation) -> NormalEquations:
        diag, off, off2, grad = _assemble(problem, ev, fixed)
        scale = np.einsum("npp->np", diag).reshape(-1) + 1e-6
        return NormalEquations(_banded(diag, off, off2), grad.reshape(-1), scale)

    start = [problem.evaluate(root, u)]
    e0 = None if start[0].mod is None else start[0].mod.energy
    fit = levenberg_marquardt(
        lambda pose: problem.evaluate(*pose),
        (root, u),
        first=start.pop(),  # the LM holds the first evaluation only until its first step
        normal_equations=normal_equations,
        solve=partial(_solve_fixed, frozen=np.repeat(fixed, p)),
        damping=Nielsen(lam=1e-4, nu=2.0, floor=1e-9),
        max_iter=iterations,
        max_tries=12,
        rtol=tol,
        retract=lambda pose, step: kin.retract(*pose, step.reshape(n, p)),
        progress=progress,
    )
    return fit, e0


def _keep_check(problem: _Problem, fit, e0, start: tuple, fixed: np.ndarray) -> np.ndarray:
    """Frames that keep their initialization: never worse than the start, a frame whose own model
    energy rose (by more than ``model_keep_ratio``) keeps it; the energies of the first and the
    last evaluation where the LM has them (``e0``, ``fit.evaluation.mod``)."""
    if problem.model is None:
        return np.zeros(0, dtype=np.int64)
    mod = fit.evaluation.mod
    e0 = _model_energy(problem, *start) if e0 is None else e0
    e1 = _model_energy(problem, *fit.x) if mod is None else mod.energy
    rise = np.maximum(problem.w.model_keep_ratio * e0, 1.0)
    return np.flatnonzero((e1 > e0 + rise) & ~fixed)


@dataclass
class SubProblem:
    """Some frames of a refinement as their own system, in local frame indices.

    ``frames`` (n,) global frame indices: the ``own`` frames being solved (ascending), then the
    closest references they use that are not among them (appended as fixed frames, each behind
    a break). ``refs`` local reference frames; ``annotations`` local frame -> annotation;
    ``closest`` (n,) local closest reference (-1 for none; an appended reference is its own);
    ``breaks`` local breaks (gaps and sequence breaks among the own frames, then one before
    every appended reference); ``extra`` the appended frames' local indices (keep them fixed).
    """

    frames: np.ndarray
    own: int
    refs: np.ndarray
    annotations: dict[int, FrameAnnotation]
    closest: np.ndarray
    breaks: list[int]
    extra: np.ndarray


def sub_problem(
    own: np.ndarray,
    closest_reference: np.ndarray,
    is_reference: np.ndarray,
    reference_annotations: dict[int, FrameAnnotation],
    sequence_breaks: Iterable[int] = (),
) -> SubProblem:
    """The sub-problem of the ascending global frames ``own`` (a piece's window, one hand's
    frames); ``closest_reference`` (N,) and ``is_reference`` (N,) bool are the whole problem's."""
    own = np.asarray(own, dtype=np.int64)
    c = closest_reference[own]
    extra = np.setdiff1d(np.unique(c[c >= 0]), own)
    frames = np.concatenate([own, extra])
    m = len(own)
    local = np.full(len(closest_reference), -1, dtype=np.int64)
    local[frames] = np.arange(len(frames))
    breaks = {int(b) for b in sequence_breaks}
    cut = [i for i in range(1, m) if own[i] != own[i - 1] + 1 or int(own[i]) in breaks]
    refs = np.flatnonzero(is_reference[frames])
    return SubProblem(
        frames=frames,
        own=m,
        refs=refs,
        annotations={
            int(i): reference_annotations[int(frames[i])]
            for i in refs
            if int(frames[i]) in reference_annotations
        },
        closest=np.concatenate([np.where(c >= 0, local[np.maximum(c, 0)], -1), local[extra]]),
        breaks=cut + list(range(m, len(frames))),
        extra=np.arange(m, len(frames)),
    )


def _refine_by_hand(table: BoneTable, init_mm, fixed: np.ndarray, t0: float, **kw) -> RefineResult:
    """:func:`refine` with several bone-length sets: the frames of each set (one person's hand,
    whole sequences, so no temporal term joins two sets) are solved as their own system with
    their own bones (:func:`sub_problem`, as a piece of :mod:`handanno_core.pieces` is).
    Energies and terms are summed over the sets."""
    init = np.asarray(init_mm, dtype=np.float64)
    n = len(init)
    closest = kw.pop("closest_reference")
    is_ref = np.zeros(n, dtype=bool)
    is_ref[np.asarray(list({int(r) for r in kw.pop("reference_frames")}), dtype=np.int64)] = True
    annotations = kw.pop("reference_annotations")
    breaks = kw.pop("sequence_breaks")
    crops, boxes, centres = kw.pop("crops"), np.asarray(kw.pop("boxes")), kw.pop("centres_mm")
    centres = np.asarray(centres)
    joints = init.copy()
    results: list[RefineResult] = []
    kept: list[int] = []
    for h in range(len(table.lengths)):
        sub = sub_problem(table.frames_of(h), closest, is_ref, annotations, breaks)
        frames, m = sub.frames, sub.own
        res = refine(
            init[frames],
            crops=crops[frames],
            boxes=boxes[frames],
            centres_mm=centres[frames],
            bone_lengths_mm=table.lengths[h],
            reference_frames=sub.refs,
            reference_annotations=sub.annotations,
            closest_reference=sub.closest,
            sequence_breaks=sub.breaks,
            fixed_frames=np.concatenate([np.flatnonzero(fixed[frames[:m]]), sub.extra]),
            **kw,
        )
        joints[frames[:m]] = res.joints_mm[:m]
        kept += [int(frames[i]) for i in res.info.get("kept_initialization", []) if i < m]
        results.append(res)
    longest = max(len(r.energy_history) for r in results)
    history = np.sum(
        [np.pad(r.energy_history, (0, longest - len(r.energy_history)), mode="edge")
         for r in results],
        axis=0,
    )  # fmt: skip
    terms: dict[str, float] = {}
    for r in results:
        for k, v in r.terms.items():
            terms[k] = terms.get(k, 0.0) + v
    return RefineResult(
        joints_mm=joints,
        energy_history=[float(e) for e in history],
        bone_violation_max_mm=max(r.bone_violation_max_mm for r in results),
        terms=terms,
        iterations=max(r.iterations for r in results),
        converged=all(r.converged for r in results),
        time_s=time.perf_counter() - t0,
        info={"hands": [r.info for r in results], "kept_initialization": sorted(kept)},
    )
