"""The engine's one Levenberg-Marquardt loop, with the linear solver and the damping rule plugged in.

A problem gives two functions:

* ``evaluate(x) -> E``: the cost at ``x`` (``E.cost``, a float) plus whatever the normal equations
  need (residuals, per-frame pieces, ...);
* ``normal_equations(x, E) -> NormalEquations``: ``JᵀJ`` (any layout its solver reads: a dense
  ``(n, n)`` matrix or a banded one), ``Jᵀr`` ``(n,)`` and the damping scale ``(n,)`` (the diagonal
  of ``JᵀJ``, Marquardt's scaling).

``solve(system, lam) -> step (n,)`` solves ``(JᵀJ + lam diag(scale)) step = -Jᵀr``
(:func:`solve_dense`, :func:`solve_banded`, or a ``functools.partial`` of a problem's own);
``retract(x, step)`` moves ``x`` by the step (``x + step`` by default; a manifold for poses). A step
is accepted when the cost drops; otherwise the damping grows and the step is solved again, up to
``max_tries`` times per iteration. It stops when no step is accepted, after ``max_iter``
iterations, or when an accepted step lowers the cost by less than ``rtol * cost + atol``.

Damping rules: :class:`Marquardt` (divide/multiply by constant factors) and :class:`Nielsen`
(H. B. Nielsen, "Damping parameter in Marquardt's method", IMM-REP-1999-05: update on the gain
ratio of actual to predicted decrease).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.linalg import LinAlgError
from scipy.linalg import solveh_banded

from .blas import single_blas_thread

__all__ = [
    "LMResult",
    "Marquardt",
    "Nielsen",
    "NormalEquations",
    "levenberg_marquardt",
    "solve_banded",
    "solve_dense",
]


@dataclass
class NormalEquations:
    """``matrix``: ``JᵀJ`` in the layout its solver reads; ``gradient``: ``Jᵀr (n,)``; ``scale``:
    ``(n,)`` diagonal the damping multiplies."""

    matrix: Any
    gradient: np.ndarray
    scale: np.ndarray

    def predicted_decrease(self, step: np.ndarray, lam: float) -> float:
        """Decrease of the damped quadratic model for ``step``: ``½ stepᵀ(lam·scale·step − Jᵀr)``."""
        return 0.5 * float(step @ (lam * self.scale * step - self.gradient))


def solve_dense(system: NormalEquations, lam: float) -> np.ndarray:
    """Damped step from a dense ``(n, n)`` ``JᵀJ``."""
    m = system.matrix.copy()
    m[np.diag_indices(len(m))] += lam * system.scale
    return np.linalg.solve(m, -system.gradient)


def solve_banded(system: NormalEquations, lam: float) -> np.ndarray:
    """Damped step from a symmetric banded ``JᵀJ`` in ``scipy.linalg.solveh_banded``'s upper form
    (last row = diagonal)."""
    ab = system.matrix
    diagonal = ab[-1].copy()  # damped in place and restored: one copy of the band, not two
    ab[-1] += lam * system.scale
    try:
        with single_blas_thread():
            return solveh_banded(ab, -system.gradient, lower=False, check_finite=False)
    finally:
        ab[-1] = diagonal


class _HasCost(Protocol):
    cost: float


class Damping(Protocol):
    lam: float

    def accept(self, gain: float) -> None: ...

    def reject(self) -> None: ...


@dataclass
class Marquardt:
    """``lam /= down`` after an accepted step (not below ``floor``), ``lam *= up`` after a rejected
    one."""

    lam: float = 1e-4
    up: float = 10.0
    down: float = 0.1
    floor: float = 1e-9

    def accept(self, gain: float) -> None:
        self.lam = max(self.lam * self.down, self.floor)

    def reject(self) -> None:
        self.lam *= self.up


@dataclass
class Nielsen:
    """Nielsen's rule: after an accepted step with gain ratio ``ρ``,
    ``lam *= max(1/3, 1 - (2 min(ρ, 1) - 1)^3)`` (not below ``floor``); after a rejected one
    ``lam *= nu`` and ``nu`` doubles."""

    lam: float = 1e-4
    nu: float = 2.0
    floor: float = 1e-9

    def accept(self, gain: float) -> None:
        self.lam = max(
            self.lam * max(1.0 / 3.0, 1.0 - (2.0 * min(gain, 1.0) - 1.0) ** 3), self.floor
        )
        self.nu = 2.0

    def reject(self) -> None:
        self.lam *= self.nu
        self.nu *= 2.0


@dataclass
class LMResult:
    """``x``/``evaluation``: the last accepted point and its evaluation; ``history``: cost before
    the first and after every iteration; ``log``: ``(iteration, lam, tries, gain)`` per iteration
    (gain 0 when no step was accepted)."""

    x: Any
    evaluation: Any
    iterations: int
    converged: bool
    lam: float
    history: list[float] = field(default_factory=list)
    log: list[tuple[int, float, int, float]] = field(default_factory=list)


def _add(x: np.ndarray, step: np.ndarray) -> np.ndarray:
    return x + step.reshape(np.shape(x))


def levenberg_marquardt(
    evaluate: Callable[[Any], _HasCost],
    x0: Any,
    *,
    normal_equations: Callable[[Any, Any], NormalEquations],
    solve: Callable[[NormalEquations, float], np.ndarray] = solve_dense,
    damping: Damping | None = None,
    max_iter: int = 25,
    max_tries: int = 5,
    rtol: float = 1e-8,
    atol: float = 0.0,
    retract: Callable[[Any, np.ndarray], Any] = _add,
    progress: Callable[[int, float], None] | None = None,
    first: _HasCost | None = None,
) -> LMResult:
    """Minimise ``evaluate(x).cost`` from ``x0`` (see the module docstring).

    ``first``: ``evaluate(x0)`` when the caller already has it. ``progress(iteration, cost)`` is
    called after every iteration. A solver raising ``LinAlgError``/``ValueError`` counts as a
    rejected try."""
    damping = damping if damping is not None else Marquardt()
    x = x0
    ev = first if first is not None else evaluate(x0)
    out = LMResult(x, ev, 0, False, damping.lam, [ev.cost])
    for it in range(1, max_iter + 1):
        out.iterations = it
        system = normal_equations(x, ev)
        trial = None
        tries = 0
        while tries < max_tries:
            tries += 1
            try:
                step = solve(system, damping.lam)
            except (LinAlgError, ValueError):
                damping.reject()
                continue
            x_n = retract(x, step)
            trial = evaluate(x_n)
            if np.isfinite(trial.cost) and trial.cost < ev.cost:
                break
            trial = None
            damping.reject()
        if trial is None:
            out.history.append(ev.cost)
            out.log.append((it, damping.lam, tries, 0.0))
            out.converged = True
        else:
            predicted = system.predicted_decrease(step, damping.lam)
            gain = (ev.cost - trial.cost) / max(predicted, 1e-300)
            small = ev.cost - trial.cost < rtol * ev.cost + atol
            damping.accept(gain)
            out.log.append((it, damping.lam, tries, gain))
            x, ev = x_n, trial
            out.history.append(ev.cost)
            out.converged = small
        if progress is not None:
            progress(it, ev.cost)
        if out.converged:
            break
    out.x, out.evaluation, out.lam = x, ev, damping.lam
    return out


# ------------------------------------------------------------------------------------------------
# many small independent problems at once
# ------------------------------------------------------------------------------------------------
@dataclass
class BatchedNormalEquations:
    """Per-row ``JᵀJ`` ``(M, P, P)``, ``Jᵀr`` ``(M, P)`` and damping: row ``i`` solves
    ``(JᵀJ_i + (lam_i · scale_i + shift) I) step_i = -Jᵀr_i``."""

    matrix: np.ndarray
    gradient: np.ndarray
    scale: np.ndarray
    shift: float = 0.0

    def solve(self, lam: np.ndarray) -> np.ndarray:
        eye = np.eye(self.matrix.shape[-1])
        damp = (lam[:, None] * self.scale + self.shift)[:, :, None] * eye
        return np.linalg.solve(self.matrix + damp, -self.gradient[..., None])[..., 0]


def _where_rows(mask: np.ndarray, new, old):
    """Row-wise choice between two states (arrays with a leading row axis, or tuples/dicts of
    them)."""
    if isinstance(new, tuple):
        return tuple(_where_rows(mask, a, b) for a, b in zip(new, old, strict=True))
    if isinstance(new, dict):
        return {k: _where_rows(mask, new[k], old[k]) for k in new}
    m = mask.reshape(mask.shape + (1,) * (np.ndim(new) - 1))
    return np.where(m, new, old)


def _take_rows(state, idx):
    """Rows ``idx`` of a row-wise state (as :func:`_where_rows`)."""
    if isinstance(state, tuple):
        return tuple(_take_rows(a, idx) for a in state)
    if isinstance(state, dict):
        return {k: _take_rows(v, idx) for k, v in state.items()}
    return state[idx]


def _put_rows(state, idx, rows):
    """A copy of ``state`` with its rows ``idx`` replaced by ``rows``."""
    if isinstance(state, tuple):
        return tuple(_put_rows(a, idx, b) for a, b in zip(state, rows, strict=True))
    if isinstance(state, dict):
        return {k: _put_rows(state[k], idx, rows[k]) for k in state}
    out = np.array(state, copy=True)
    out[idx] = rows
    return out


@dataclass
class BatchedLMResult:
    """``x``/``evaluation``: each row's last accepted point and evaluation; ``iterations`` run."""

    x: Any
    evaluation: Any
    iterations: int


def levenberg_marquardt_batched(
    evaluate: Callable[[Any], Any],
    x0: Any,
    *,
    normal_equations: Callable[[Any, Any], BatchedNormalEquations],
    retract: Callable[[Any, np.ndarray], Any],
    max_iter: int,
    lam0: float = 1e-3,
    up: float = 10.0,
    down: float = 0.3,
    floor: float = 0.0,
    rtol: float | None = None,
    max_lam: float | None = None,
    max_rejects: int | None = None,
    first: Any = None,
    active_rows: bool = False,
) -> BatchedLMResult:
    """Levenberg-Marquardt on ``M`` independent problems at once, one trial step per iteration.

    ``evaluate(x)`` returns an evaluation with ``cost`` ``(M,)`` (and the rest a row-wise state:
    arrays with a leading ``M`` axis, or tuples/dicts of them); ``x`` likewise. A row's step is
    kept only where it lowers that row's cost; then its ``lam`` is multiplied by ``down`` (not
    below ``floor``), else by ``up``. With ``rtol``/``max_lam`` a row stops once an accepted step
    lowers its cost by less than ``rtol`` (relative) or its ``lam`` reaches ``max_lam`` or its
    step was rejected ``max_rejects`` times in a row; the loop ends when every row has stopped or
    after ``max_iter`` iterations. With ``active_rows`` only the rows still running are solved and
    evaluated: ``evaluate(x, rows)`` gets their state and indices ``rows`` (M',) and returns their
    evaluation, and ``normal_equations`` is called only for rows whose point moved since their
    last normal equations (a rejected trial costs one evaluation, no Jacobian)."""
    x = x0
    if first is not None:
        ev = first
    else:
        ev = evaluate(x0, np.arange(_num_rows(x0))) if active_rows else evaluate(x0)
    m_rows = len(ev.cost)
    lam = np.full(m_rows, lam0)
    active = np.ones(m_rows, dtype=bool)
    rejects = np.zeros(m_rows, dtype=np.int64)
    stale = np.ones(m_rows, dtype=bool)  # rows whose cached normal equations are out of date
    system = None
    it = 0
    for _ in range(max_iter):
        it += 1
        if active_rows:
            rows = np.flatnonzero(active)
            need = rows[stale[rows]]
            if len(need):
                ne = normal_equations(_take_rows(x, need), type(ev)(**_take_rows(vars(ev), need)))
                if system is None:
                    system = BatchedNormalEquations(
                        *(
                            np.zeros((m_rows,) + a.shape[1:])
                            for a in (ne.matrix, ne.gradient, ne.scale)
                        ),
                        ne.shift,
                    )
                system.matrix[need], system.gradient[need] = ne.matrix, ne.gradient
                system.scale[need] = ne.scale
                stale[need] = False
            sub = BatchedNormalEquations(
                system.matrix[rows], system.gradient[rows], system.scale[rows], system.shift
            )
            x_r = retract(_take_rows(x, rows), sub.solve(lam[rows]))
            ev_r = evaluate(x_r, rows)
            dec = ev.cost[rows] - ev_r.cost
            ok = np.isfinite(ev_r.cost) & (dec > 0)
            better = np.zeros(m_rows, dtype=bool)
            better[rows[ok]] = True
            rel = np.zeros(m_rows)
            rel[rows[ok]] = dec[ok] / np.maximum(ev.cost[rows[ok]], 1e-12)
            x = _put_rows(x, rows[ok], _take_rows(x_r, ok))
            ev = type(ev)(**_put_rows(vars(ev), rows[ok], _take_rows(vars(ev_r), ok)))
        else:
            step = normal_equations(x, ev).solve(lam)
            step[~active] = 0.0
            x_n = retract(x, step)
            ev_n = evaluate(x_n)
            better = active & np.isfinite(ev_n.cost) & (ev_n.cost < ev.cost)
            rel = np.where(better, (ev.cost - ev_n.cost) / np.maximum(ev.cost, 1e-12), 0.0)
            x = _where_rows(better, x_n, x)
            ev = type(ev)(**_where_rows(better, vars(ev_n), vars(ev)))
        lam = np.where(better, np.maximum(lam * down, floor), lam * up)
        rejects = np.where(better, 0, rejects + active)
        stale |= better
        if rtol is not None:
            active &= ~(better & (rel < rtol))
        if max_lam is not None:
            active &= lam < max_lam
        if max_rejects is not None:
            active &= rejects < max_rejects
        if not np.any(active):
            break
    return BatchedLMResult(x, ev, it)


def _num_rows(state) -> int:
    while isinstance(state, (tuple, dict)):
        state = next(iter(state.values())) if isinstance(state, dict) else state[0]
    return len(state)
