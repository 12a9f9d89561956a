"""A statistical prior over hand poses learned from real recorded motion.

A pose is described by the direction of the bone leaving every angle joint in that joint's own
frame (:meth:`handanno_core.skeleton.Skeleton.bone_directions`: along the incoming bone, towards
the palm, lateral; ``A`` joints, ``3 A`` numbers), which does not depend on where the hand is, how
it is turned, or how long its bones are. Real hands move their fingers together (a curled ring
finger drags the little finger with it), so these directions are strongly correlated; one Gaussian
over all of them (mean ``mu``, covariance ``S`` plus ``shrink`` on the diagonal) says how likely a
whole pose is, where the angle ranges only bound each joint alone.

The energy of a pose is ``1/2 |W (phi - mu)|^2`` with ``W^T W = (S + shrink I)^-1`` (half the
squared Mahalanobis distance, dimensionless). The lift adds it, times a weight, to its objective:
it decides what the clicks leave open, such as the depth of a finger the camera does not see.
:func:`session_prior` makes it one session's own (its mean, its spread).

The table (``data/pose_prior.json``) is written by ``benchmarks/learn_pose_prior.py`` from
``shared/data/real-motion`` (derived statistics only). A left hand is measured as the mirror of a
right one: the lateral component changes sign.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .skeleton import Skeleton


@dataclass(frozen=True)
class PosePrior:
    """A Gaussian over the ``(A, 3)`` bone directions of a layout's angle joints (a right hand).

    mean: ``(3 A,)``; sqrt_precision: ``(3 A, 3 A)`` ``W`` with ``W^T W`` the inverse of the
    shrunk covariance; layout: the skeleton's name; frames: how many poses it was learned from.
    """

    layout: str
    mean: np.ndarray
    sqrt_precision: np.ndarray
    frames: int = 0
    #: median :meth:`energy` of the poses it was learned from
    typical_energy: float = 1.0

    def features(self, skeleton: Skeleton, poses_mm: np.ndarray, right_hand: bool = True):
        """``(..., 3 A)`` the prior's coordinates of ``poses_mm`` ``(..., J, 3)`` mm."""
        d = skeleton.bone_directions(poses_mm, right_hand) * mirror_sign(right_hand)
        return d.reshape(*d.shape[:-2], -1)

    def residuals(self, features: np.ndarray) -> np.ndarray:
        """``(..., 3 A)`` ``W (phi - mu)``: the pose's energy is half its squared norm."""
        return (np.asarray(features) - self.mean) @ self.sqrt_precision.T

    def feature_energy(self, features: np.ndarray) -> np.ndarray:
        """``(...)`` half the squared Mahalanobis distance of ``features`` ``(..., 3 A)``."""
        return 0.5 * np.sum(self.residuals(features) ** 2, axis=-1)

    def energy(self, skeleton: Skeleton, poses_mm: np.ndarray, right_hand: bool = True):
        """``(...)`` half the squared Mahalanobis distance of each pose (dimensionless)."""
        return self.feature_energy(self.features(skeleton, poses_mm, right_hand))


def mirror_sign(right_hand: bool) -> np.ndarray:
    """``(3,)`` what a bone direction (along, towards the palm, lateral) is multiplied by to be
    measured as a right hand's: a left hand is a mirrored right one, its lateral side reversed."""
    return np.array([1.0, 1.0, 1.0 if right_hand else -1.0])


def learn_pose_prior(
    skeleton: Skeleton, poses_mm: np.ndarray, shrink: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """The mean ``(3 A,)`` and shrunk covariance ``(3 A, 3 A)`` of the bone directions of
    ``poses_mm`` ``(N, J, 3)`` mm (right hands). ``shrink`` is added to the diagonal: each
    component of a unit direction may vary by at least ``sqrt(shrink)`` (0.1, about 6 degrees),
    also where the recordings never moved it."""
    d = skeleton.bone_directions(np.asarray(poses_mm, dtype=np.float64))
    phi = d.reshape(len(d), -1)
    ok = np.all(np.isfinite(phi), axis=1)
    if ok.sum() < 2 * phi.shape[1]:
        raise ValueError(f"{int(ok.sum())} usable poses: too few for a {phi.shape[1]}-d prior")
    phi = phi[ok]
    mean = phi.mean(axis=0)
    cov = np.cov(phi, rowvar=False) + shrink * np.eye(phi.shape[1])
    return mean, cov


def prior_from_moments(
    layout: str,
    mean: np.ndarray,
    cov: np.ndarray,
    frames: int = 0,
    keep: np.ndarray | None = None,
    typical_energy: float = 1.0,
) -> PosePrior:
    """A :class:`PosePrior` from a mean ``(3 A,)`` and a positive definite covariance. ``keep``
    ``(A,)`` bool: the angle joints the prior speaks about (the marginal over them; the others'
    directions are free), default all."""
    mean = np.asarray(mean, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    dims = np.ones(len(mean), dtype=bool) if keep is None else np.repeat(np.asarray(keep, bool), 3)
    sub = cov[np.ix_(dims, dims)]
    # W = L^-1 with cov = L L^T: W^T W = cov^-1 (of the kept directions' marginal)
    low = np.linalg.cholesky(0.5 * (sub + sub.T))
    w = np.zeros((len(mean), len(mean)))
    w[np.ix_(dims, dims)] = np.linalg.solve(low, np.eye(len(sub)))
    return PosePrior(layout, mean, w, frames, typical_energy)


def default_pose_prior_path() -> Path:
    """The packaged table of pose priors per layout."""
    return Path(__file__).resolve().parent / "data" / "pose_prior.json"


@functools.cache
def _table() -> dict:
    path = default_pose_prior_path()
    if not path.is_file():
        return {}
    return json.loads(path.read_text())["layouts"]


def pose_prior(skeleton: Skeleton) -> PosePrior | None:
    """The packaged prior of ``skeleton``'s layout, or None if it has none (or a different
    number of angle joints)."""
    return _packaged(skeleton.name, 3 * len(skeleton.angle_joints))


@functools.cache
def _packaged(layout: str, size: int) -> PosePrior | None:
    row = _table().get(layout)
    if row is None or len(row["mean"]) != size:
        return None
    keep = np.array([name not in row["free"] for name in row["joints"]])
    return prior_from_moments(
        layout, row["mean"], row["covariance"], row["frames"], keep, row["typical_energy"]
    )


def session_scale(prior: PosePrior, energies: np.ndarray) -> float:
    """How much wider than the prior a session's poses are: the median of their energies
    ``energies`` (e.g. its lifted references') over the energy typical of the poses the prior
    was learned from, at least 1. Dividing the prior's weight by it widens the prior for a hand
    that moves unlike the recordings (another person, a generator) instead of pulling its poses
    towards theirs."""
    e = np.asarray(energies, dtype=np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return 1.0
    return max(1.0, float(np.median(e)) / max(prior.typical_energy, 1e-9))


def session_prior(
    prior: PosePrior,
    skeleton: Skeleton,
    poses_mm: np.ndarray,
    weight: float,
    right_hand: bool = True,
    pseudo_count: float = 5.0,
    widen: bool = False,
) -> tuple[PosePrior, float]:
    """The prior made for one session from its lifted poses ``poses_mm`` ``(N, J, 3)`` mm: its
    mean moved to the poses' own mean (weighted ``N`` against ``pseudo_count`` for the learned
    one), and the weight ``weight`` divided by :func:`session_scale` of the poses under it.

    Why: the bone directions at the knuckles depend on the shape of the palm (where the knuckles
    sit relative to the wrist), which differs from person to person and from a renderer's hand;
    the learned mean would pull every pose towards the recorded person's palm. The session's own
    mean keeps what real hands share, the correlations between the fingers.

    ``widen``: the poses' own spread about their mean is added to the covariance (only ever
    wider), so the ways this hand moves that the recordings did not (a renderer's fingers moving
    one at a time) are not pulled back, while what neither shows stays held; the hand-model fit
    uses it (:func:`handanno_core.handmodel.personalize`), the lift does not."""
    feats = prior.features(skeleton, poses_mm, right_hand)
    feats = feats[np.all(np.isfinite(feats), axis=1)]
    if len(feats) == 0:
        return prior, weight
    n = float(len(feats))
    mean = (n * feats.mean(axis=0) + pseudo_count * prior.mean) / (n + pseudo_count)
    moved = dataclasses.replace(prior, mean=mean)
    if widen and len(feats) > 1:
        moved = _widened(moved, feats)
    return moved, weight / session_scale(moved, moved.feature_energy(feats))


def _widened(prior: PosePrior, feats: np.ndarray) -> PosePrior:
    """``prior`` with the spread of ``feats`` ``(N, 3 A)`` about their mean added to its
    covariance: the directions a session moves in are not penalized more than the recordings'."""
    w = prior.sqrt_precision
    kept = np.any(w != 0, axis=0)
    wk = w[np.ix_(kept, kept)]
    cov = np.eye(len(prior.mean))
    d = feats - feats.mean(axis=0)
    cov[np.ix_(kept, kept)] = np.linalg.inv(wk.T @ wk) + (d.T @ d)[np.ix_(kept, kept)] / len(d)
    keep = kept.reshape(-1, 3).all(axis=1)
    return prior_from_moments(
        prior.layout, prior.mean, cov, prior.frames, keep, prior.typical_energy
    )
