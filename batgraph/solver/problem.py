"""The smoother's problem: the observation rows, the cameras, one motion model with a noise level per marker, the
robust loss and the gauge priors; its cost and its Gauss-Newton system at a state.

The cost (every backend minimises this one), for the M markers of a problem over F frames:
- per observation row: rho(|L^-1 (pi_c(p(t)) - uv)|^2), pi_c the pinhole to ideal pixels, L L^T the ideal
  pixel covariance, rho the robust loss (:class:`Loss`), p(t) the marker's position at the row's capture time
  t = frame + s (batgraph.solver.model.interpolation between the states of the frames around it);
- per marker and frame step: 0.5 e^T Q^-1 e, e = x[k+1] - A x[k] (the motion model; Q = Q1 noise_scale(level));
- per marker: 0.5 (x[0] - mu0)^T P0 (x[0] - mu0), the weak gauge prior on the first frame.
States x are (F, M, d) in the scaled units of batgraph.solver.model (every block in metres).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..camera import Rig
from ..measurement import IdealObservations
from . import kernels
from . import model as mm

LOSSES = tuple(kernels.ROBUST_CODE)


@dataclass(frozen=True)
class Loss:
    """The robust loss on projection rows: "huber", "cauchy" or "none", threshold k in whitened units."""

    name: str = "huber"
    k: float = 2.0

    def __post_init__(self):
        if self.name not in LOSSES:
            raise ValueError(f"robust loss must be one of {LOSSES}, got {self.name!r}")

    @property
    def code(self) -> int:
        return kernels.ROBUST_CODE[self.name]

    def rho_w(self, d2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rho, IRLS weight) of squared whitened norms d2 (any shape)."""
        d2 = np.asarray(d2, float)
        rho, w = kernels.robust_loss(d2.ravel(), self.code, float(self.k))
        return rho.reshape(d2.shape), w.reshape(d2.shape)


@dataclass(frozen=True)
class Cameras:
    """The rig as the rows use it: P (12, C) the projection matrices K [R | t] to ideal pixels, row-major, and
    behind (C,) the residual [px] of a point behind a camera (2 fx, GTSAM's cheirality answer)."""

    P: np.ndarray
    behind: np.ndarray

    @classmethod
    def of(cls, rig: Rig) -> Cameras:
        return cls(np.ascontiguousarray(np.stack([c.P.ravel() for c in rig], axis=-1)),
                   np.array([2.0 * c.K[0, 0] for c in rig]))


@dataclass
class Rows:
    """Observation rows sorted by (marker, frame, camera): marker, frame, cam (n,) int; uv (2, n) ideal pixels;
    Linv (3, n) the whitening (a, b, c) of L^-1 = [[a, 0], [b, c]], L = chol(cov); s (n,) the capture time after
    its frame [frames]; row (n,) the raw image row / height (a rolling shutter's regressor); n_markers.
    Placed for a model (:meth:`placed`): k (n,) the first frame of the interval holding the capture time,
    W, dW (n, 2, 3) the weights of the position (and of its derivative in time) on the states of k and k + 1."""

    marker: np.ndarray
    frame: np.ndarray
    cam: np.ndarray
    uv: np.ndarray
    Linv: np.ndarray
    s: np.ndarray
    row: np.ndarray
    n_markers: int
    k: np.ndarray | None = field(default=None, repr=False)
    W: np.ndarray | None = field(default=None, repr=False)
    dW: np.ndarray | None = field(default=None, repr=False)

    @property
    def starts(self) -> np.ndarray:
        """Each marker's first row (n_markers + 1,)."""
        return np.searchsorted(self.marker, np.arange(self.n_markers + 1))

    def placed(self, name: str, n_frames: int) -> Rows:
        """These rows with k, W and dW for model ``name`` over ``n_frames`` frames (a capture time outside the
        frames is extrapolated from the end state by the model's mean)."""
        t = self.frame + self.s
        k = np.floor(t).astype(np.int64)
        W, dW = np.zeros((len(t), 2, 3)), np.zeros((len(t), 2, 3))
        inside = (k >= 0) & (k < n_frames - 1)
        W[inside], dW[inside] = _each_distinct(lambda u: mm.interpolation(name, u), t[inside] - k[inside])
        for end, sel in ((0, k < 0), (n_frames - 1, k >= n_frames - 1)):
            W[sel, 0], dW[sel, 0] = _each_distinct(lambda u: mm.extrapolation(name, u), t[sel] - end)
            k[sel] = end
        return replace(self, k=k, W=W, dW=dW)

    def shifted(self, ds: np.ndarray) -> Rows:
        """These rows with their capture times moved by ds (n,) [frames] (placement to be done again)."""
        return replace(self, s=self.s + ds, k=None, W=None, dW=None)

    def of_markers(self, keep: np.ndarray) -> Rows:
        """The rows of the markers where ``keep`` (bool (n_markers,)), markers renumbered; placement kept."""
        new = np.cumsum(keep) - 1
        sel = np.flatnonzero(keep[self.marker])
        rows = (lambda a: None if a is None else np.ascontiguousarray(a[sel]))  # noqa: E731
        return Rows(new[self.marker[sel]], self.frame[sel], self.cam[sel], np.ascontiguousarray(self.uv[:, sel]),
                    np.ascontiguousarray(self.Linv[:, sel]), self.s[sel], self.row[sel], int(keep.sum()),
                    rows(self.k), rows(self.W), rows(self.dW))

    @classmethod
    def of(cls, ideal: IdealObservations, markers: np.ndarray | None = None) -> Rows:
        """Every observation of ``markers`` (int indices; default all) of ``ideal``, markers numbered in order."""
        seen = ideal.seen
        if markers is not None:
            seen = seen[:, :, markers]
        m, f, c = np.nonzero(seen.transpose(2, 1, 0))  # sorted by (marker, frame, camera)
        mk = m if markers is None else np.asarray(markers)[m]
        cov = ideal.cov_px2[c, f, mk]
        l00 = np.sqrt(cov[:, 0, 0])
        l10 = cov[:, 1, 0] / l00
        l11 = np.sqrt(cov[:, 1, 1] - l10 * l10)
        Linv = np.stack([1 / l00, -l10 / (l00 * l11), 1 / l11])
        tf, rf = getattr(ideal, "time_frac", None), getattr(ideal, "row_frac", None)
        s = np.zeros(len(m)) if tf is None else tf[c, f, mk].astype(float)
        row = np.zeros(len(m)) if rf is None else rf[c, f, mk].astype(float)
        return cls(m, f, np.ascontiguousarray(c), np.ascontiguousarray(ideal.uv_px[c, f, mk].T),
                   np.ascontiguousarray(Linv), s, row, int(seen.shape[2]))


def _each_distinct(weights, tau: np.ndarray) -> tuple:
    """weights(tau) (a pair of arrays (n, ...)), computed once where every tau is the same (a synchronised rig's
    rows all have tau = 0), else per row (a rolling shutter gives almost every row its own)."""
    if len(tau) and tau.min() == tau.max():
        return tuple(np.repeat(a, len(tau), axis=0) for a in weights(tau[:1]))
    return weights(tau)


@dataclass
class Problem:
    """The cost of M markers (module docstring) with one motion model ``model`` and a noise level per marker,
    level (M,) (sigma_m [m], q [m^2/s^3] or j [m^2/s^5]); mu0 (M, 3) the gauge prior's mean positions [m].
    prior: (mean (M, d), information (M, d, d)) on the first frame's state instead of the gauge prior (the
    filter's prediction)."""

    rows: Rows
    cams: Cameras
    fps: float
    n_frames: int
    model: str
    level: np.ndarray
    loss: Loss
    mu0: np.ndarray
    prior: tuple | None = None

    def __post_init__(self):
        mm.check(self.model)
        if self.rows.k is None:
            self.rows = self.rows.placed(self.model, self.n_frames)
        self.level = np.broadcast_to(np.asarray(self.level, float), (self.rows.n_markers,)).copy()
        self.A, Q1, self.P0 = mm.scaled(self.model, 1.0 / self.fps)
        self.Qi1 = np.linalg.inv(Q1)
        self.Qi1 = 0.5 * (self.Qi1 + self.Qi1.T)

    @property
    def d(self) -> int:
        return mm.state_dim(self.model)

    @property
    def n_markers(self) -> int:
        return self.rows.n_markers

    @property
    def wq(self) -> np.ndarray:
        """1 / noise_scale per marker (M,): Q^-1 = wq Qi1."""
        return 1.0 / mm.noise_scale(self.model, self.level)

    def with_level(self, level: np.ndarray) -> Problem:
        return replace(self, level=np.asarray(level, float))

    def of_markers(self, keep: np.ndarray) -> Problem:
        """The problem of the markers where ``keep`` (bool (M,))."""
        prior = None if self.prior is None else (self.prior[0][keep], self.prior[1][keep])
        return replace(self, rows=self.rows.of_markers(keep), level=self.level[keep], mu0=self.mu0[keep],
                       prior=prior)

    def motion_blocks(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A^T Q^-1 A, Q^-1, -Q^-1 A), each (M, d, d): the motion part's blocks of the Hessian."""
        Qi = self.wq[:, None, None] * self.Qi1
        return np.einsum("ji,mjk,kl->mil", self.A, Qi, self.A), Qi, -Qi @ self.A

    def motion_cost(self, x: np.ndarray) -> np.ndarray:
        """0.5 sum_k e_k^T Q^-1 e_k per marker (M,), e = x[k+1] - A x[k]."""
        if len(x) < 2:
            return np.zeros(x.shape[1])
        e = x[1:] - x[:-1] @ self.A.T
        return 0.5 * self.wq * np.einsum("fmi,fmi->m", e @ self.Qi1, e)

    def prior_cost(self, x: np.ndarray) -> np.ndarray:
        mean, info = self._prior()
        e0 = x[0] - mean
        return 0.5 * (e0 * (info @ e0[..., None])[..., 0]).sum(axis=-1)

    def _prior(self) -> tuple[np.ndarray, np.ndarray]:
        """The first frame's prior: (mean (M, d), information (M, d, d))."""
        if self.prior is not None:
            return self.prior
        mu = np.zeros((self.n_markers, self.d))
        mu[:, :3] = self.mu0
        return mu, np.broadcast_to(self.P0, (self.n_markers, self.d, self.d))

    def cost(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(total cost per marker (M,), inf where not finite; each marker's largest inverse depth (M,) [1/m])."""
        cost, near = np.zeros(self.n_markers), np.zeros(self.n_markers)
        kernels.rows_system(np.ascontiguousarray(x), self.rows, self.cams, self.loss, _NONE, cost, near)
        total = cost + self.motion_cost(x) + self.prior_cost(x)
        return np.where(np.isnan(total), np.inf, total), near

    def system(self, x: np.ndarray, exact: np.ndarray | bool = False) -> tuple:
        """(cost (M,), near (M,), D (F, M, d, d), B (F - 1, M, d, d), g (F, M, d)) at x: the Gauss-Newton blocks
        (H[k + 1, k] in B) and gradient; the rows' curvature is the robust loss's own where ``exact`` (per
        marker), IRLS's elsewhere."""
        cost, near, D, B, g = self.row_system(x, exact)
        cost = cost + self.add_motion(x, D, B, g)
        return np.where(np.isnan(cost), np.inf, cost), near, D, B, g

    def row_system(self, x: np.ndarray, exact: np.ndarray | bool = False) -> tuple:
        """:meth:`system`'s projection rows alone (cost (M,) not made finite)."""
        F, M, d = x.shape
        cost, near = np.zeros(M), np.zeros(M)
        D, B, g = np.zeros((F, M, d, d)), np.zeros((max(F - 1, 0), M, d, d)), np.zeros((F, M, d))
        ex = np.ascontiguousarray(np.broadcast_to(np.asarray(exact, float), (M,)))
        kernels.rows_system(np.ascontiguousarray(x), self.rows, self.cams, self.loss, ex, cost, near, (D, B, g))
        return cost, near, D, B, g

    def add_motion(self, x: np.ndarray, D: np.ndarray, B: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Add the motion and gauge-prior terms at x to a system (D, B, g), in place; returns their cost (M,)."""
        mean, info = self._prior()
        D[0] += info
        e0 = x[0] - mean
        ge0 = (info @ e0[..., None])[..., 0]
        g[0] += ge0
        cost = 0.5 * (e0 * ge0).sum(axis=-1)
        if len(x) < 2:
            return cost
        AtQiA, Qi, Bm = self.motion_blocks()
        e = x[1:] - x[:-1] @ self.A.T
        eQ = np.einsum("fmi,mij->fmj", e, Qi)
        g[:-1] -= eQ @ self.A
        g[1:] += eQ
        D[:-1] += AtQiA
        D[1:] += Qi
        B += Bm
        return cost + 0.5 * np.einsum("fmi,fmi->m", e, eQ)


_NONE = np.zeros(1)


def start_state(name: str, fps: float, p: np.ndarray, v: np.ndarray | None = None,
                a: np.ndarray | None = None) -> np.ndarray:
    """The scaled state (F, M, d) of model ``name`` from positions p [m], velocities v [m/s] and accelerations
    a [m/s^2], each (F, M, 3); v defaults to np.gradient(p) fps, a to np.gradient(v) fps."""
    d, dt = mm.state_dim(name), 1.0 / fps
    x = np.zeros(p.shape[:2] + (d,))
    x[..., :3] = p
    if d >= 6:
        v = gradient(p, fps) if v is None else v
        x[..., 3:6] = v * dt
        if d == 9:
            x[..., 6:9] = (gradient(v, fps) if a is None else a) * dt * dt
    return x


def derivatives(x: np.ndarray, fps: float) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(velocities [m/s], accelerations [m/s^2]) (..., 3) of scaled states x (..., d); None where the model has none."""
    d = x.shape[-1]
    return (x[..., 3:6] * fps if d >= 6 else None), (x[..., 6:9] * fps * fps if d == 9 else None)


def gradient(a: np.ndarray, fps: float) -> np.ndarray:
    """d a / dt along frames (axis 0), np.gradient times fps; zero for a single frame."""
    return np.gradient(a, axis=0) * fps if len(a) > 1 else np.zeros_like(a)


def log_det_units(name: str, fps: float, n_frames: int) -> float:
    """What to add to a log det of the information in scaled states to have it in physical units."""
    return 2 * n_frames * mm.log_det_scale(name, 1.0 / fps)

