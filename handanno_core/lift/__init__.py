"""Lift annotated reference frames from 2D to 3D (thesis Eq. 3), and estimate the bone lengths.

For one frame, :func:`lift_frame` solves, with SLSQP and analytic gradients/Jacobians,

    min_X  1/2 sum_k a_k |pi(X_k) - uv_k|^2                   (px^2, joints with 2D)
         + 1/2 w_3d   sum_k a_k |X_k - xyz_k|^2                (px^2/mm^2 * mm^2, joints placed in 3D)
         + 1/2 w_surf sum_k (z_k - D_k - o_k - s)^2            (visible joints with depth)
         + 1/2 w_flat sum_k (z_k - z_parent)^2                 (hidden joints, no depth order)
         + 1/2 w_free sum_k |X_k - X0_k|^2                     (unannotated joints only)
         + 1/2 w_angle sum_r min(g_r(X), 0)^2                  (angle-range rows, mm; soft)
         + w_pose E_prior(X)                                   (pose prior, px^2)
    s.t.   |X_c - X_p| = d_b                                   (bones, equality, mm)
           D_k + o_k <= z_k <= D_k + o_k + eps                 (visible joints with valid depth; bounds)
           D_k + o_k <= z_k                                    (occluded joints with valid depth; bounds)
           sigma_k (z_k - z_parent) >= margin                  (annotated depth order, sigma = +-1)

``a_k`` is 1 for a clicked or dragged joint and :data:`ACCEPTED_UV_WEIGHT` (1/4) for a guess
the annotator accepted without moving it (``FrameAnnotation.accepted``; in 3D: a review
correction's joints seeded where they were shown, :func:`handanno_core.review.seed_annotation`,
weighed like an accepted 2D guess rather than with a constant of their own): an accepted guess lies
anywhere within about 4 px (``review_loop.CLICK_PX``) of where the annotator would click (2.8
px RMS if spread evenly over that disc), a click about 1.4 px, so an accepted position is about
twice as uncertain and the clicks, depths and bones may move it further. On the suite's tune
part 1/4 lifted the pre-filled references closer to the truth than 1 at the same clicks, and
1/16 further from it (HISTORY.md, stop 37).

``D_k`` is the observed depth at the joint's 2D position (the median of the front surface in the
3x3 block: its pixels within 10 mm of the closest one; the nearest valid pixel in a small window
where the block has none) and ``o_k`` the skeleton's surface offset (about the finger radius, 0 at
the tips). The median, not the closest pixel: the closest of 9 noisy readings lies about 1.5
sensor noise SDs in front of the surface, a bias that differs between sensors (SR300-like noise:
1.3-1.8 mm; ``depth_front_band_mm``).

Why the surface term: with exact 2D the one-sided depth intervals leave the whole hand free to
slide up to ``eps`` along the viewing rays, and with noisy 2D a foreshortened bone turns a pixel of
noise into centimetres of depth. The pull towards ``D_k + o_k + s_k`` (``w_surface`` = 0.1
px^2/mm^2; ``surface_depth_mm`` ``s_k`` per kind of joint, :data:`solve.SURFACE_DEPTH_MM`: 1 mm
for the wrist, finger joints and tips, 2 mm for the knuckles, whose centre lies a knuckle radius
below the surface, deeper than their offsets say; chosen on the suite's tune part) fixes visible
joints near where joint centres lie. Hidden joints without a depth order only have a lower
bound; where the two mirror poses of a hidden finger both fit the 2D (bones nearly parallel to the
image), ``w_flat`` (0.01 px^2/mm^2) prefers the one closer to the parent's depth (figures:
``benchmarks/results/design_measurements.md``).

Inclined fingers (:mod:`handanno_core.lift.surface`): where a visible finger joint's bone is
inclined to the viewing ray (a finger pointing away from or towards the camera), the ray through
the joint centre enters the segment's cylinder ``r / sin(phi)`` before the centre, not ``r``. After
a solve, the visible PIP/DIP-level joints' surface targets and upper bounds are moved by
``o (k / sin(phi) - 1)`` for the pose found (``k`` = ``incline_radius_factor``, the finger radius
over the offset; ``phi`` the angle to the covering bone, ``sin`` capped at ``incline_min_sin``) and
the frame is solved again from that pose (at most twice; ``LiftResult.surface_extra_mm``).
A hidden joint whose covering segment is inclined lies at least as deep behind whatever is seen
at its pixel (the ray through its centre enters its own segment ``r / sin(phi)`` before it): its
lower depth bound ``D + o`` becomes ``D + o + extra`` (``incline_hidden``; never above the truth
on the suite's tune part, and a bound, not a target: the joint may lie behind another finger).
Fingertips whose distal segment leads away from the camera lie on the far end of its cap: their
target moves by ``2 k o_dip cos(phi)`` (``incline_tips``). A warm start (``init_mm``: the previous
round's pose, a dragged joint) begins with the targets of its start pose, so the re-solve only
runs where the solution moves them by 0.5 mm or more.

The pose prior (:mod:`handanno_core.pose_prior`): ``E_prior`` is half the squared Mahalanobis
distance of the bone directions in the angle joints' frames from a Gaussian learned on real
recorded hands (FPHA, without the benchmark suite's sequences). It decides what the clicks leave
open, above all the depth of the fingers the camera does not see: real fingers curl together.
:func:`lift_references` makes it the session's own after its first round
(:func:`handanno_core.pose_prior.session_prior`): the mean moves to the lifted references' (the
knuckles' directions depend on the palm's shape, which differs between people), and ``w_pose``
(:data:`solve.W_POSE` = 0.3 px^2, chosen on the suite's tune part) is divided by how much wider
than the learned spread the session's poses still are (``LiftSet.pose_weight``). A single
:func:`lift_frame` (the app's live lift and pre-fill) has no prior unless given ``w_pose``: the
learned prior, not yet the session's, pulls another person's hand towards the recorded one's.

Observed depths that no pose can meet (a visible bone whose two readings differ by more than its
length + eps) are dropped before solving: a 2D point that slips off a thin finger reads the
surface behind it, or the finger in front of it (see :func:`initial_pose`).

Joint angles follow ``skeleton.joint_angles`` exactly (same palm normal, same frame: lateral axis
from the palm normal at a finger's first joint, transported along the chain after that). The
ranges are ``skeleton.angle_ranges()``: the anatomical limits widened to what real hands were
recorded doing (robust percentiles over FPHA / NYU / ICVL motion, ``data/angle_ranges.json``).
They are *soft*: a row ``g_r >= 0`` holds inside the range, and beyond it the penalty
``w_angle/2 g_r^2`` (``g_r`` ~ bone length x sin(excess angle), mm) grows quadratically instead of a
hard wall (real hands exceed any fixed limits now and then; a wall turns that into a wrong pose
elsewhere). A flexion range of 170 degrees or more has no rows (no limit). The rows are linear in
the outgoing bone ``b`` for a fixed local frame (``a_hat``, ``n_perp``, ``lateral``):

* flexion >= fmin:  cos(fmin) b.n_perp - sin(fmin) b.a_hat >= 0   (a half-plane; range < 180 deg)
* flexion <= fmax:  sin(fmax) b.a_hat - cos(fmax) b.n_perp >= 0
* abduction in [amin, amax]:  |b| sin(amin) <= b.lateral <= |b| sin(amax)

The frame depends on the incoming bones of the chain and on the palm normal; all are
differentiated exactly (no lagged frame).

If the hard problem is infeasible or SLSQP fails (typically a 2D point on the wrong surface, so
its observed depth is wrong), the frame is re-solved in *elastic mode*: each depth interval gets a
slack with an L1 cost (an exact penalty: intervals that can be met are met). A result whose bone or
order constraints are still violated by more than 0.5 mm is returned with
``converged=False`` and halved confidence. An infeasible hard solve is recognised early: its
constraint violation stays stuck at its first value, and a callback stops it once the violation
(> 5 mm) has not dropped for 4 iterations instead of letting it run to the iteration limit. A feasible iterate that merely ran
out of iterations is kept (not re-solved). The app's live re-lift passes ``start_elastic`` for a
frame whose previous lift needed slack, skipping the hard attempt altogether, and
``elastic_joints`` = the joints that needed it, so only those get slack variables (the others keep
hard bounds: a smaller problem, the same solution where the guess is right, and a fallback to
slacks on every joint where it is not); both are :class:`WarmStart` fields.

Speed notes: scipy's SLSQP calls LAPACK; with a multithreaded OpenBLAS on a loaded machine each call
can be 50x slower, so every solve runs inside :func:`handanno_core.blas.single_blas_thread`.
Variables are offsets from the initial pose, scaled per axis (1.5 mm units in x/y ~ 1 px, 10 mm
in z) so SLSQP's identity start Hessian is about right; constraints are in mm. The soft angle
penalty's gradient is back-propagated through the rows and frames (reverse mode, vectorized over
fingers, one batch per chain level; no Jacobian matrix) and skipped where every row is inside its
range.

Bone lengths (:func:`lift_references`) are unknown in advance. They start from the skeleton's
template scaled to the annotated frames and are re-estimated from all lifted references: each
round lifts every reference with *soft* bones (a penalty towards the current estimate instead of
hard equalities), so a frame whose 2D/depth evidence cannot be met with the current length
stretches or shrinks the bone; the new estimate is the median over frames where both of the
bone's joints are annotated (at least ``min_bone_votes`` references; a bone with fewer keeps the
template times the global scale of the re-estimated bones, so a partially annotated hand of any
size gets all its bones). A bone *seen* in ``min_bone_votes`` references or more (both ends
visible with a reading the lift kept, the bone not foreshortened: the sine of its angle to the
image below 0.7) takes the median over those references only: a hidden joint's soft length is its
start length again, so its vote is the prior's, not data. Rounds stop when no bone moves by more
than 0.1 mm (at most 30 rounds: where no reference measures a hidden finger, its bones move by
only 0.1-0.2 mm a round, each round a step of a slow fixed-point iteration, and a limit of 10
stopped them before they settled on the suite's tune part, HISTORY.md stop 52); a final lift
uses the estimate as hard constraints, from both the last soft solution and the cold start,
keeping the lower objective (the soft rounds can drift into the mirrored mode of a hidden
finger). With ``shrink_bones`` each median is pulled towards the template's
proportions by its own uncertainty (:func:`references.shrink_to_template`); ``handanno lift`` uses
it only in its second estimate for noisy clicks (``pipeline.lift``).

Surface offsets are self-calibrated per session (:func:`surface_correction`): once the bones have
converged, the median over annotated visible joints of ``z_lifted - (D + o + s)`` per joint group
(same level along the chains) corrects that group's offset, and the rounds continue with the
corrected offsets (at most ``max_calibrations`` times). Fingertips are the anchor and are not
corrected: from 2D and depth alone, moving every joint deeper below the surface is the same as a
larger hand farther away (an exact scale ambiguity of the projection), so only the *relative*
depth of joint groups (a wrist or palm joint deeper inside the hand than the default, as on NYU)
is recoverable this way. The offsets used are returned in ``LiftSet.surface_offsets_mm``.

A reference whose own soft-bone lift wants an annotated bone more than 20 % (and 3 mm, and 4 robust
standard deviations of the bone's spread over the references) longer or shorter than the final
estimate is reported ``stretched`` and not ``converged`` (with a warning):
the template could only be fitted to its clicks by stretching it.
"""

from ..annotation import AnnotationError
from .initial import initial_bone_lengths, initial_pose, observed_depth
from .references import LiftSet, lift_references, surface_correction
from .solve import ACCEPTED_UV_WEIGHT, LiftResult, WarmStart, lift_frame

__all__ = [
    "ACCEPTED_UV_WEIGHT",
    "LiftResult",
    "LiftSet",
    "WarmStart",
    "initial_bone_lengths",
    "initial_pose",
    "lift_frame",
    "lift_references",
    "observed_depth",
    "surface_correction",
    "AnnotationError",
]
