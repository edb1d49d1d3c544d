"""GTSAM's factor graph of the smoother's cost (batgraph.solver.problem): the reference the fast backend is tested
against, and ``--solver gtsam``.

Variables per marker and frame: p (Point3 [m]), u = v dt and w = a dt^2 (Point3 as vectors [m]) as the model has
them, so every block shares a unit (GTSAM's Cholesky declares a clique indeterminate when the diagonal of its R
spans more than 2^12); a segment's length is a 1-vector [m]. Factors: a projection row captured at its frame's
time is GTSAM's TriangulationFactor on p; one captured between frames is a CustomFactor on the states around it
(the model's interpolation, batgraph.solver.model); motion factors are linear (a LinearContainerFactor of the
whitened rows, exact); gauge priors are PriorFactorPoint3; segment lengths CustomFactors. Levenberg-Marquardt
and every factorisation use QR: a marker seen by one camera for a few dozen frames has a depth variance 1e6-1e8
times its lateral one, which GTSAM's Cholesky rejects (gtsam.Marginals failed at q = 1e4 on a simulated flight).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from ..camera import Camera
from . import fit as fit_mod
from . import lm
from .backends import choose_fast
from .problem import Cameras, Loss, Problem, Rows, derivatives, log_det_units, start_state
from .segments import Segments, groups, initial_lengths

_BITS = 32


def state_key(block: int, m: int, k: int) -> int:
    """Key of block ``block`` (0 p, 1 u, 2 w) of marker m's state at frame k."""
    return gtsam.symbol("xvw"[block], (m << _BITS) | k)


def length_key(s: int) -> int:
    return gtsam.symbol("l", s)


def pose_key(c: int) -> int:
    """Key of camera c's pose (Pose3, world_from_cam) when it is a variable."""
    return gtsam.symbol("c", c)


def _noise(cov_or_Linv: np.ndarray, loss) -> gtsam.noiseModel.Base:
    """The row's Gaussian noise (from its whitening L^-1 = [[a, 0], [b, c]]), robust as ``loss``."""
    a, b, c = cov_or_Linv
    Linv = np.array([[a, 0.0], [b, c]])
    base = gtsam.noiseModel.Gaussian.Information(Linv.T @ Linv)  # (SqrtInformation reads an upper triangle)
    if loss.name == "none":
        return base
    est = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[loss.name]
    return gtsam.noiseModel.Robust.Create(est.Create(loss.k), base)


def _calibration(cam: Camera) -> gtsam.Cal3_S2:
    K = cam.K
    return gtsam.Cal3_S2(K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2])


def _camera(cam: Camera) -> gtsam.PinholeCameraCal3_S2:
    R_wc, t_wc = cam.world_from_cam()
    return gtsam.PinholeCameraCal3_S2(gtsam.Pose3(gtsam.Rot3(R_wc), t_wc), _calibration(cam))


def _interpolated_error(P: np.ndarray, behind: float, uv: np.ndarray, weights: np.ndarray):
    """The error function of a row between frames: pi(sum_j weights[j] x_j) - uv over its state keys."""

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        keys = this.keys()
        p = sum(w * values.atPoint3(k) for w, k in zip(weights, keys, strict=True))
        hom = P @ np.append(p, 1.0)
        if not hom[2] > 0:
            if H is not None:
                for i in range(len(keys)):
                    H[i] = np.zeros((2, 3))
            return np.full(2, behind)
        u = hom[:2] / hom[2]
        if H is not None:
            J = (P[:2, :3] - np.outer(u, P[2, :3])) / hom[2]
            for i, w in enumerate(weights):
                H[i] = w * J
        return u - uv

    return error


class Graph:
    """The graph of one :class:`Problem` (and one segment group's segments when given), with initial values."""

    def __init__(self, problem: Problem, rig, x0: np.ndarray, seg: Segments | None = None, L0=None):
        self.problem, self.graph, self.values = problem, gtsam.NonlinearFactorGraph(), gtsam.Values()
        F, M, d = x0.shape
        self.nb = d // 3
        for m in range(M):
            for k in range(F):
                for j in range(self.nb):
                    self.values.insert(state_key(j, m, k), x0[k, m, 3 * j:3 * j + 3])
        self._rows(problem, rig)
        self._motion(problem, F, M)
        if seg is not None:
            self._segments(seg, F, L0)

    def _rows(self, problem: Problem, rig) -> None:
        r = problem.rows
        cams = [_camera(c) for c in rig]
        for i in range(len(r.k)):
            noise = _noise(r.Linv[:, i], problem.loss)
            m, k, c = int(r.marker[i]), int(r.k[i]), int(r.cam[i])
            w = r.W[i]
            if w[0, 0] == 1.0 and not w[0, 1:].any() and not w[1].any():
                self.graph.push_back(gtsam.TriangulationFactorCal3_S2(cams[c], r.uv[:, i], noise, state_key(0, m, k)))
                continue
            keys, weights = [], []
            for e in range(2):
                for j in range(self.nb):
                    if w[e, j] != 0.0:
                        keys.append(state_key(j, m, k + e))
                        weights.append(w[e, j])
            self.graph.push_back(gtsam.CustomFactor(
                noise, keys, _interpolated_error(rig[c].P, problem.cams.behind[c], r.uv[:, i], weights)))

    def _motion(self, problem: Problem, F: int, M: int) -> None:
        mean, info = problem._prior()
        AtQiA, Qi, _ = problem.motion_blocks()
        d = problem.d
        for m in range(M):
            R = np.linalg.cholesky(info[m]).T
            self.graph.push_back(_linear(R, mean[m], [state_key(j, m, 0) for j in range(self.nb)]))
            if F < 2:
                continue
            W = np.linalg.cholesky(Qi[m]).T @ np.hstack([-problem.A, np.eye(d)])
            for k in range(F - 1):
                keys = [state_key(j, m, k) for j in range(self.nb)] + [state_key(j, m, k + 1) for j in range(self.nb)]
                self.graph.push_back(_linear(W, np.zeros(2 * d), keys))

    def _segments(self, seg: Segments, F: int, L0: np.ndarray) -> None:
        noise = gtsam.noiseModel.Isotropic.Sigma(1, seg.sigma)
        for s, (a, b) in enumerate(seg.local):
            self.values.insert(length_key(s), np.array([L0[s]]))
            for k in range(F):
                self.graph.push_back(gtsam.CustomFactor(
                    noise, [state_key(0, int(a), k), state_key(0, int(b), k), length_key(s)], _segment_error))

    def solve(self) -> tuple[gtsam.Values, int]:
        params = gtsam.LevenbergMarquardtParams()
        params.setRelativeErrorTol(1e-12)
        params.setAbsoluteErrorTol(1e-15)
        params.setMaxIterations(lm.TIGHT.max_iterations)
        params.setLinearSolverType("MULTIFRONTAL_QR")
        opt = gtsam.LevenbergMarquardtOptimizer(self.graph, self.values, params)
        return opt.optimize(), int(opt.iterations())

    def states(self, values: gtsam.Values, F: int, M: int) -> np.ndarray:
        x = np.zeros((F, M, 3 * self.nb))
        for m in range(M):
            for k in range(F):
                for j in range(self.nb):
                    x[k, m, 3 * j:3 * j + 3] = values.atPoint3(state_key(j, m, k))
        return x

    def marginals(self, values: gtsam.Values, keys: list[int]) -> np.ndarray:
        """Marginal covariances of ``keys`` through a QR iSAM2 Bayes tree (gtsam.Marginals has no QR option)."""
        params = gtsam.ISAM2Params()
        params.setFactorization("QR")
        params.enableRelinearization = False
        isam = gtsam.ISAM2(params)
        isam.update(self.graph, values)
        return np.array([isam.marginalCovariance(k) for k in keys])

    def logdet(self, values: gtsam.Values) -> float:
        """log det of the Gauss-Newton information at ``values`` (scaled states), from a QR Bayes net."""
        lin = self.graph.linearize(values)
        net = lin.eliminateSequential(gtsam.Ordering.ColamdGaussianFactorGraph(lin), gtsam.EliminateQR)
        return 2.0 * sum(np.log(np.abs(np.diag(net.at(i).R()))).sum() for i in range(net.size()))


def _linear(W: np.ndarray, b: np.ndarray, keys: list[int]) -> gtsam.NonlinearFactor:
    """0.5 |W (x - b)|^2 over the 3-vectors of ``keys`` (x stacked in that order) as a CustomFactor (exact: linear)."""
    noise = gtsam.noiseModel.Unit.Create(len(W))
    blocks = [W[:, 3 * i:3 * i + 3] for i in range(len(keys))]

    def error(this, values, H):
        x = np.concatenate([values.atPoint3(k) for k in keys])
        if H is not None:
            for i in range(len(keys)):
                H[i] = blocks[i]
        return W @ (x - b)

    return gtsam.CustomFactor(noise, keys, error)


def _segment_error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
    ka, kb, kl = this.keys()
    diff = values.atPoint3(ka) - values.atPoint3(kb)
    dist = float(np.linalg.norm(diff))
    if H is not None:
        u = (diff / max(dist, 1e-9)).reshape(1, 3)
        H[0], H[1], H[2] = u, -u, -np.ones((1, 1))
    return np.array([dist - values.atVector(kl)[0]])


@dataclass(frozen=True)
class Reference:
    """The GTSAM backend (module docstring); its noise search is the fast one (the same evidence, tested)."""

    name: str = "gtsam"

    def fit(self, setup, models, levels, start, settings=lm.TIGHT, covariances=True, with_segments=True):
        F, M = setup.shape
        out = fit_mod.Fit.empty(F, M, covariances)
        solved = np.array([m is not None for m in models])
        found = groups(setup.pairs, solved) if with_segments else []
        grouped = np.zeros(M, bool)
        for members, _ in found:
            grouped[members] = True
        units = [(np.array([m]), None) for m in np.flatnonzero(solved & ~grouped)] + list(found)
        for members, seg_ids in units:
            _fit_unit(setup, models, levels, start, members, seg_ids, covariances, out)
        return out

    def choose(self, setup, start, candidates, groups, progress):
        return choose_fast(setup, start, candidates, groups, progress)


REFERENCE = Reference()


def _fit_unit(setup, models, levels, start, members, seg_ids, covariances, out) -> None:
    """Solve one marker, or one segment group, by GTSAM into ``out``."""
    name = models[members[0]]
    F = setup.shape[0]
    prob = setup.problem(members, name, levels[members])
    x0 = start_state(name, setup.fps, *(None if a is None else a[:, members] for a in start))
    seg, L0 = None, None
    if seg_ids is not None:
        seg = Segments(np.searchsorted(members, setup.pairs[seg_ids]), setup.rigid_sigma_m)
        L0 = initial_lengths(x0[..., :3], seg.local, setup.ideal.seen.any(axis=0)[:, members])
    g = Graph(prob, setup.rig, x0, seg, L0)
    values, iters = g.solve()
    x = g.states(values, F, len(members))
    out.state[:, members, :x.shape[-1]] = x
    out.models[members] = name
    out.xyz[:, members] = x[..., :3]
    v, a = derivatives(x, setup.fps)
    if v is not None:
        out.velocity[:, members] = v
    if a is not None:
        out.acceleration[:, members] = a
    if covariances:
        keys = [state_key(0, i, k) for k in range(F) for i in range(len(members))]
        out.cov[:, members] = g.marginals(values, keys).reshape(F, len(members), 3, 3)
    out.cost[members] = g.graph.error(values) / len(members)
    out.logdet[members] = 0.0
    out.logdet[members[0]] = g.logdet(values) + log_det_units(name, setup.fps, F) * len(members)
    out.iterations[members], out.converged[members] = iters, iters < lm.TIGHT.max_iterations
    if seg is not None:
        lengths = np.array([values.atVector(length_key(s))[0] for s in range(len(seg.local))])
        sd = np.sqrt(g.marginals(values, [length_key(s) for s in range(len(seg.local))])[:, 0, 0])
        out.pairs = np.concatenate([out.pairs, setup.pairs[seg_ids]])
        out.length_m, out.length_sd_m = np.concatenate([out.length_m, lengths]), np.concatenate([out.length_sd_m, sd])




RELINEARIZE_THRESHOLD = 1e-5  # [m]: iSAM2 relinearises a variable when its delta exceeds it


def run_filter(session, ideal, motion: tuple[str, float], joins: tuple, loss: Loss, on_frame=None) -> tuple:
    """The filter by GTSAM's iSAM2 fed one frame at a time (the reference of batgraph.solver.filter): a marker
    joins at its first frame with a triangulation (joins: frames (M,), -1 never, and points (M, 3) [m]), with the
    gauge priors there; from then on it gets its state on every frame, the motion factor (motion: model, level)
    even when unobserved. A camera with a pose covariance is a Pose3 variable under that prior (the paper's eq. 10
    as shared variables: its uncertainty reaches every marker). Returns (xyz (F, M, 3), cov (F, M, 3, 3), the
    number of camera variables)."""
    name, level = motion
    join, tri = joins
    C, F, M = ideal.seen.shape
    rows = Rows.of(ideal)
    rows = rows.placed(name, F)
    prob = Problem(rows, Cameras.of(session.rig), session.fps, F, name, np.full(M, level), loss, np.zeros((M, 3)))
    isam = _isam()
    nb = prob.d // 3
    cams = [_camera(c) for c in session.rig]
    cals = [_calibration(c) for c in session.rig]  # owned here: the factors keep shared pointers to them
    variable = np.array([c.pose_cov is not None for c in session.rig])
    graph0, values0 = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for c in np.flatnonzero(variable):
        graph0.push_back(gtsam.PriorFactorPose3(pose_key(int(c)), cams[c].pose(),
                                                gtsam.noiseModel.Gaussian.Covariance(session.rig[int(c)].pose_cov)))
        values0.insert(pose_key(int(c)), cams[c].pose())
    if variable.any():
        isam.update(graph0, values0)
    last = np.zeros((M, prob.d))
    xyz, cov = np.full((F, M, 3), np.nan), np.full((F, M, 3, 3), np.nan)
    _, Qi, _ = prob.motion_blocks()
    W = np.linalg.cholesky(Qi[0]).T @ np.hstack([-prob.A, np.eye(prob.d)])
    R0 = np.linalg.cholesky(prob.P0).T
    for k in range(F):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for m in np.flatnonzero((join >= 0) & (join <= k)):
            if join[m] == k:
                last[m] = 0.0
                last[m, :3] = tri[m]
                graph.push_back(_linear(R0, last[m].copy(), [state_key(j, int(m), k) for j in range(nb)]))
            else:
                last[m] = prob.A @ last[m]
                keys = [state_key(j, int(m), k - 1) for j in range(nb)] + [state_key(j, int(m), k) for j in range(nb)]
                graph.push_back(_linear(W, np.zeros(2 * prob.d), keys))
            for j in range(nb):
                values.insert(state_key(j, int(m), k), last[m, 3 * j:3 * j + 3])
        on = np.flatnonzero((rows.frame == k) & (join[rows.marker] >= 0) & (join[rows.marker] <= k))
        for i in on:
            noise, c, key = _noise(rows.Linv[:, i], loss), int(rows.cam[i]), state_key(0, int(rows.marker[i]), k)
            if variable[c]:
                graph.push_back(gtsam.GenericProjectionFactorCal3_S2(rows.uv[:, i], noise, pose_key(c), key, cals[c]))
            else:
                graph.push_back(gtsam.TriangulationFactorCal3_S2(cams[c], rows.uv[:, i], noise, key))
        isam.update(graph, values)
        isam.update()  # one relinearising step more: the newest points' first linearisation is at the prediction
        ms = np.flatnonzero((join >= 0) & (join <= k))
        for m in ms:
            for j in range(nb):
                last[m, 3 * j:3 * j + 3] = isam.calculateEstimatePoint3(state_key(j, int(m), k))
            xyz[k, m] = last[m, :3]
            cov[k, m] = isam.marginalCovariance(state_key(0, int(m), k))
        if on_frame is not None:
            on_frame(k, xyz[k], cov[k])
    return xyz, cov, int(variable.sum())


def _isam() -> gtsam.ISAM2:
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(RELINEARIZE_THRESHOLD)
    params.relinearizeSkip = 1
    params.setFactorization("QR")
    return gtsam.ISAM2(params)
