"""The crop geometry spec (:class:`CropSpec`, :data:`DEFAULT_CROP`), re-exported by
:mod:`handanno_core.crops`.

Its own module, importing nothing of the package, so that :mod:`handanno_core.localize` (which
:mod:`handanno_core.crops` imports) can take its defaults from :data:`DEFAULT_CROP` too.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

__all__ = ["CropSpec", "DEFAULT_CROP"]


@dataclass(frozen=True)
class CropSpec:
    """The one home of crop geometry: a cube of ``cube_mm`` (edge, mm) around each frame's centre,
    resampled to ``size x size`` pixels, depth normalized to ``(d - z_c) / half_mm``.

    ``BACKGROUND`` (+1) is the value of every crop pixel that is not hand (no depth, behind the
    cube, far in front of it); :meth:`is_background` is the one test for it. A session's spec is
    :meth:`of` its settings; :func:`handanno_core.crops.locate_crops` may grow the cube (a larger hand).
    """

    cube_mm: float = 220.0
    size: int = 128
    BACKGROUND: ClassVar[float] = 1.0

    @property
    def half_mm(self) -> float:
        """Half the cube edge (mm): a normalized crop value of 1 is this far behind the centre."""
        return 0.5 * self.cube_mm

    @classmethod
    def of(cls, settings) -> CropSpec:
        """The spec of session ``settings`` (anything with ``cube_mm`` and ``crop_size``)."""
        return cls(float(settings.cube_mm), int(settings.crop_size))

    def with_cube(self, cube_mm: float) -> CropSpec:
        return replace(self, cube_mm=float(cube_mm))

    @staticmethod
    def is_background(values: np.ndarray) -> np.ndarray:
        """Boolean mask of background crop values (``>= BACKGROUND``, float16-safe)."""
        return np.asarray(values) >= CropSpec.BACKGROUND - 1e-3

    def depth_mm(self, values: np.ndarray, centre_z_mm: np.ndarray) -> np.ndarray:
        """Camera depth (mm) of normalized crop ``values`` for centres at depth ``centre_z_mm``
        (broadcast); background values are meaningless here (mask them with
        :meth:`is_background`)."""
        return np.asarray(centre_z_mm, np.float64) + np.asarray(values, np.float64) * self.half_mm


#: the default spec (new sessions start from it).
DEFAULT_CROP = CropSpec()
