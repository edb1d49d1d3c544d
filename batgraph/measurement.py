"""The measurement model every estimator shares: raw pixels -> ideal pixels with mapped noise.

Distortion is removed once, here (the paper does the same), and the pixel noise is carried through
the undistortion's Jacobian: a raw-pixel covariance ``S = (sigma^2 / weight) I`` becomes
``J S J^T`` on ideal pixels, J = d(ideal)/d(raw) at the observation. The estimators then use a plain
pinhole ``uv_ideal = K [x/z, y/z]``. Why not GTSAM's Cal3DS2: it has no k3, which GoPro lenses
need; this route handles all five coefficients, and batgraph.solver tests it against Cal3DS2 on
a k3 = 0 rig.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .camera import Rig
from .session import DenseObservations


@dataclass
class IdealObservations:
    """uv_px: ideal pixels, shape (C, F, M, 2), NaN where unseen.
    cov_px2: their noise covariance, shape (C, F, M, 2, 2) [px^2], NaN where unseen.
    linear_xyz: (rig, positions (F, M, 3) [m]) once batgraph.triangulate.dlt_points has triangulated these pixels
    with that rig (they depend on nothing else, so :meth:`with_sigma` keeps them): the self-checks' linear
    triangulation is then the smoother's and the triangulation method's start, not computed again (0.2-0.3 s
    each at 30 x 180 x 160). The pixels are never changed in place (batgraph.measurement.without
    makes new ones).
    time_frac, row_frac: (C, F, M) or None, as batgraph.session.DenseObservations has them: each observation's
    capture time minus its frame's, in frames, from the rig's known timing; its raw row / image height.
    """

    uv_px: np.ndarray
    cov_px2: np.ndarray
    linear_xyz: tuple | None = field(default=None, repr=False, compare=False)
    time_frac: np.ndarray | None = None  # (C, F, M) capture time after the frame's [frames]; None: all 0
    row_frac: np.ndarray | None = None  # (C, F, M) raw image row / height (a rolling shutter's regressor)

    @property
    def seen(self) -> np.ndarray:
        return np.isfinite(self.uv_px[..., 0])

    def with_sigma(self, pixel_sigma_px: float | np.ndarray) -> IdealObservations:
        """These observations, made with a 1 px raw-pixel noise, at another noise: one value or (C,) [px].

        The same as ``ideal_observations(rig, dense, pixel_sigma_px)`` (the covariance scales with sigma^2)
        without undistorting again.
        """
        sigma = np.broadcast_to(np.asarray(pixel_sigma_px, dtype=float), self.uv_px.shape[:1])
        return dataclasses.replace(self, cov_px2=self.cov_px2 * (sigma ** 2)[:, None, None, None, None])

    def take(self, sl: slice) -> IdealObservations:
        """The frames ``sl`` (one take) on their own (views); the linear triangulation is not carried."""
        return _each_array(self, lambda a: a[:, sl])


def ideal_observations(rig: Rig, dense: DenseObservations, pixel_sigma_px: float | np.ndarray) -> IdealObservations:
    """Undistort every observation and map its noise (see module docstring).

    pixel_sigma_px: raw-pixel noise std [px], one value or one per camera (C,).
    """
    C = len(rig)
    sigma = np.broadcast_to(np.asarray(pixel_sigma_px, dtype=float), (C,))
    uv = np.full_like(dense.uv_px, np.nan)
    cov = np.full(dense.uv_px.shape + (2,), np.nan)
    seen = dense.seen
    for c in range(C):
        s = seen[c]
        raw = dense.uv_px[c][s]
        cam = rig[c]
        uv[c][s], J = cam.undistort_with_jacobian(raw)
        var = sigma[c] ** 2 / dense.weight[c][s]
        cov[c][s] = var[:, None, None] * (J @ np.swapaxes(J, -1, -2))
    return IdealObservations(uv, cov, time_frac=dense.time_frac, row_frac=dense.row_frac)


def of_markers(ideal: IdealObservations, markers: np.ndarray) -> IdealObservations:
    """The observations of ``markers`` (int indices or a bool mask over M): every (C, F, M, ...) array sliced."""
    return _each_array(ideal, lambda a: a[:, :, markers])


def without(ideal: IdealObservations, drop: np.ndarray) -> IdealObservations:
    """The observations with those where ``drop`` (bool (C, F, M)) made unseen (NaN pixels)."""
    uv = ideal.uv_px.copy()
    uv[drop] = np.nan
    return dataclasses.replace(ideal, uv_px=uv)


def _each_array(ideal: IdealObservations, op) -> IdealObservations:
    shape = ideal.uv_px.shape[:3]
    changes = {f.name: op(getattr(ideal, f.name)) for f in dataclasses.fields(ideal)
               if isinstance(getattr(ideal, f.name), np.ndarray) and getattr(ideal, f.name).shape[:3] == shape}
    return dataclasses.replace(ideal, **changes, linear_xyz=None)
