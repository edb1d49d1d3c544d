"""The solver core (batgraph.solver) against independent references: GTSAM's graph of the same cost, dense linear
algebra, the Gaussian-process formulas of the motion models, finite differences, and simulated truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.linalg import expm

from batgraph import checks, motion, wingbeat
from batgraph.measurement import of_markers
from batgraph.motion import constant_acceleration_Q, constant_velocity_Q
from batgraph.result import Options
from batgraph.session import dense_observations
from batgraph.simulate import Timing, simulate_flight
from batgraph.solver import backends, chains, fit, kernels, lm, reference, schedule, search, shared, threads
from batgraph.solver import model as mm
from batgraph.solver.problem import Loss, start_state
from batgraph.triangulate import dlt_points


def _scene(n_markers=6, n_frames=40, seed=1, timing=None, rigid=False):
    """A small simulated flight: (session, setup (Huber), models helper)."""
    s = simulate_flight(np.random.default_rng(seed), n_cameras=5, n_frames=n_frames, timing=timing)
    dense = dense_observations(s, timing=timing is not None or None)
    pre = checks.preflight(s, dense)
    sel = np.arange(n_markers)
    ideal = of_markers(pre.ideal, sel)
    p_init, v_init, _ = schedule.initial_track(dlt_points(s.rig, ideal), s.fps)
    pairs = fit.segments.pairs_of(s.rigid, [dense.markers[i] for i in sel]) if rigid else np.zeros((0, 2), int)
    setup = fit.Setup(ideal, pre.session.rig, s.fps, Loss(), p_init, pairs, s.rigid_sigma_m)
    return s, setup, (p_init, v_init, None)


@pytest.mark.parametrize("name", mm.MODELS[1:])
def test_interpolation_is_the_gaussian_process_posterior_mean(name):
    """model.interpolation's weights equal the GP interpolation Lambda = Phi(s) - Q_s Phi(1 - s)^T Q_1^-1 Phi(1),
    Psi = Q_s Phi(1 - s)^T Q_1^-1 of the model's own transition and noise (batgraph.motion, physical units), for
    any noise level; their derivative in s matches finite differences."""
    dt = 1 / 120
    order = mm.ORDER[name]
    n = order + 1
    gen = np.diag(np.ones(n - 1), 1)  # d/dt of [p, v, a]
    Qf = {1: constant_velocity_Q, 2: constant_acceleration_Q}[order]
    for s in (0.0, 0.23, 0.5, 0.91):
        Phi = lambda t: expm(gen * t * dt)  # noqa: E731
        Q = lambda t: Qf(7.0, t * dt)[::3, ::3] if t > 0 else np.zeros((n, n))  # noqa: E731  (one axis)
        Lam = Phi(s) - Q(s) @ Phi(1 - s).T @ np.linalg.inv(Q(1)) @ Phi(1)
        Psi = Q(s) @ Phi(1 - s).T @ np.linalg.inv(Q(1))
        S = np.diag(dt ** np.arange(n))  # physical -> scaled state: x = S [p, v, a]
        W, dW = mm.interpolation(name, np.array([s]))
        np.testing.assert_allclose(W[0, 0, :n], Lam[0] @ np.linalg.inv(S), atol=1e-9)
        np.testing.assert_allclose(W[0, 1, :n], Psi[0] @ np.linalg.inv(S), atol=1e-9)
        h = 1e-6
        num = (mm.interpolation(name, np.array([s + h]))[0] - mm.interpolation(name, np.array([s - h]))[0]) / (2 * h)
        np.testing.assert_allclose(dW, num, atol=1e-6)


def test_tridiagonal_sweeps_equal_dense_linear_algebra():
    """kernels.tridiagonal on random SPD block-tridiagonal systems (B per frame) equals numpy on the dense matrix:
    the solve, log det, diagonal blocks of the inverse and tr(H^-1 H_m) for a motion part."""
    rng = np.random.default_rng(0)
    F, M, d = 7, 3, 6
    B = rng.normal(size=(F - 1, M, d, d)) * 0.3
    D = np.zeros((F, M, d, d))
    for k in range(F):
        X = rng.normal(size=(M, d, d))
        D[k] = X @ np.swapaxes(X, -1, -2) + 5 * np.eye(d)
    rhs = rng.normal(size=(F, M, d, 2))
    Bm, AtQiA = rng.normal(size=(M, d, d)) * 0.2, np.tile(np.eye(d), (M, 1, 1))
    Qi = np.tile(2 * np.eye(d), (M, 1, 1))
    out = kernels.tridiagonal(D, B[:, :, None], rhs=rhs, marginals=True, motion=(AtQiA, Qi, Bm))
    for m in range(M):
        H = np.zeros((F * d, F * d))
        Hm = np.zeros((F * d, F * d))
        for k in range(F):
            H[k * d:(k + 1) * d, k * d:(k + 1) * d] = D[k, m]
            Hm[k * d:(k + 1) * d, k * d:(k + 1) * d] = (AtQiA[m] if k < F - 1 else 0) + (Qi[m] if k > 0 else 0)
        for k in range(F - 1):
            H[(k + 1) * d:(k + 2) * d, k * d:(k + 1) * d] = B[k, m]
            H[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] = B[k, m].T
            Hm[(k + 1) * d:(k + 2) * d, k * d:(k + 1) * d] = Bm[m]
            Hm[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] = Bm[m].T
        Hi = np.linalg.inv(H)
        np.testing.assert_allclose(out["dx"][:, m].reshape(F * d, 2), Hi @ rhs[:, m].reshape(F * d, 2), rtol=1e-10)
        np.testing.assert_allclose(out["logdet"][m], np.linalg.slogdet(H)[1], rtol=1e-12)
        for k in range(F):
            np.testing.assert_allclose(out["Sigma"][k, m], Hi[k * d:(k + 1) * d, k * d:(k + 1) * d], rtol=1e-9,
                                       atol=1e-14)
        np.testing.assert_allclose(out["trace"][m], np.trace(Hi @ Hm), rtol=1e-10)


@pytest.mark.parametrize("name,level", [("random_walk", 0.01), ("constant_velocity", 5.0),
                                        ("constant_acceleration", 3e4)])
def test_fast_backend_equals_gtsam_graph(name, level):
    """The fast backend's minimiser, marginal covariances and log det equal GTSAM's on the same cost (its graph:
    TriangulationFactor rows, linear motion factors, QR Levenberg-Marquardt and marginals). 6 markers x 40 frames
    with Huber; measured 7e-8 m, 1e-6 relative, 2e-6."""
    _, setup, start = _scene()
    models, levels = np.full(6, name, object), np.full(6, level)
    a = backends.FAST.fit(setup, models, levels, start)
    b = reference.REFERENCE.fit(setup, models, levels, start)
    np.testing.assert_allclose(a.xyz, b.xyz, atol=1e-6)
    np.testing.assert_allclose(a.cov, b.cov, atol=1e-4 * np.abs(a.cov).max())
    np.testing.assert_allclose(a.cost.sum(), b.cost.sum(), rtol=1e-8)
    np.testing.assert_allclose(a.logdet.sum(), b.logdet.sum(), rtol=1e-8)


def test_rows_between_frames_equal_gtsam_custom_factors():
    """Cameras out of step (offsets of a fraction of a frame, a 6 ms rolling shutter, the timing given): every row
    lies between two frames, so its position is the model's interpolation of the states around it (the kernel's
    pair blocks in D and B). GTSAM's graph with a CustomFactor per such row agrees: positions 1e-6 m, covariances
    1e-4 relative. And the time really matters: the same rows taken at their frames' times move the answer by mm."""
    timing = Timing(time_offsets_s=(0.0, 3.1e-3, -2.4e-3, 1.7e-3, -4.0e-3), readout_s=6e-3, known=True)
    _, setup, start = _scene(n_markers=4, n_frames=30, timing=timing)
    assert np.abs(setup.ideal.time_frac).max() > 0.3
    models, levels = np.full(4, "constant_velocity", object), np.full(4, 8.0)
    a = backends.FAST.fit(setup, models, levels, start)
    b = reference.REFERENCE.fit(setup, models, levels, start)
    np.testing.assert_allclose(a.xyz, b.xyz, atol=1e-6)
    np.testing.assert_allclose(a.cov, b.cov, atol=1e-4 * np.abs(a.cov).max())
    at_frames = backends.FAST.fit(dataclasses.replace(setup, ideal=dataclasses.replace(
        setup.ideal, time_frac=np.zeros_like(setup.ideal.time_frac))), models, levels, start)
    assert np.nanmax(np.abs(at_frames.xyz - a.xyz)) > 2e-3


def test_segments_equal_gtsam():
    """A segment group (4 markers, 3 segments, constant velocity) solved as one bordered column equals GTSAM's graph
    with segment-length CustomFactors: positions, covariances and lengths."""
    _, setup, start = _scene(n_markers=5, n_frames=30, rigid=True)
    assert len(setup.pairs) >= 2
    models, levels = np.full(5, "constant_velocity", object), np.full(5, 5.0)
    a = backends.FAST.fit(setup, models, levels, start)
    b = reference.REFERENCE.fit(setup, models, levels, start)
    np.testing.assert_allclose(a.xyz, b.xyz, atol=1e-6)
    np.testing.assert_allclose(a.length_m, b.length_m, atol=1e-7)
    np.testing.assert_allclose(a.cov, b.cov, atol=1e-3 * np.abs(a.cov).max())


def test_evidence_slope_equals_finite_differences():
    """chains.evidence_slope, d log evidence / d ln level at the minimiser, equals the finite difference of the
    Laplace evidence over +-1 % in the level (it leaves out how the rows' weights move: measured within 1 %)."""
    _, setup, start = _scene(n_markers=3)
    prob = setup.problem(np.arange(3), "constant_velocity", np.full(3, 6.0))
    x0 = start_state("constant_velocity", setup.fps, *(a[:, :3] if a is not None else None for a in start))
    sol = chains.solve(prob, x0, slope=True)

    def ev(factor):
        p = prob.with_level(prob.level * factor)
        return chains.solve(p, sol.x, covariances=False).log_evidence(p)

    num = (ev(1.01) - ev(1 / 1.01)) / (2 * np.log(1.01))
    np.testing.assert_allclose(sol.slope, num, rtol=0.02, atol=0.05)


def test_search_finds_each_markers_maximum():
    """search.choose's level is each marker's evidence maximum: the evidence there beats +-0.1 decade, and "auto"
    keeps the model of larger evidence."""
    _, setup, start = _scene(n_markers=4)
    template = setup.problem(np.arange(4), "constant_velocity", np.ones(4))
    ch = search.choose(template, tuple(None if a is None else a[:, :4] for a in start), mm.AUTO_CANDIDATES)
    for name in mm.AUTO_CANDIDATES:
        mine = ch.model == name
        if not mine.any():
            continue
        prob = setup.problem(np.flatnonzero(mine), name, ch.level[mine])
        x = ch.solution[name][:, mine, :prob.d]
        best = chains.solve(prob, x, lm.LOOSE).log_evidence(prob)
        for f in (10**0.1, 10**-0.1):
            p = prob.with_level(prob.level * f)
            assert (chains.solve(p, x, lm.LOOSE).log_evidence(p) <= best + 0.05).all()
    assert (ch.log_evidence >= np.max(np.stack(list(ch.evidence_by_model.values())), axis=0) - 1e-9).all()


def test_noise_free_scene_is_recovered():
    """Without pixel noise, and a noise stated so small (1e-5 px) that the data outweigh any motion prior, the
    smoother recovers the simulated truth on frames seen by >= 2 cameras to 1e-6 m: STYLE's first check."""
    s = simulate_flight(np.random.default_rng(3), n_cameras=5, n_frames=40, pixel_sigma_px=0.0)
    s = dataclasses.replace(s, pixel_sigma_px=1e-5)
    dense = dense_observations(s)
    pre = checks.preflight(s, dense)
    est = schedule.run_smoother(pre.session, dense, pre.ideal, Options(progress=False, accel_psd_m2_s3=10.0))
    truth = np.stack([s.truth[s.truth.marker == m].sort_values("frame")[["x", "y", "z"]].to_numpy()
                      for m in dense.markers], axis=1)
    seen = dense.n_views >= 2
    assert np.nanmax(np.abs(est.xyz_m[seen] - truth[seen])) < 1e-6


def test_shared_gradient_and_curvature_equal_finite_differences():
    """The reduced problem of the shared variables (offsets, readouts and poses): the gradient at the markers'
    minimiser equals the finite difference of the minimised cost (envelope theorem), the Schur complement its
    curvature within 5 % (Gauss-Newton's, without the rows' second derivatives)."""
    timing = Timing(time_offsets_s=(0.0, 3.1e-3, -2.4e-3, 1.7e-3, -4.0e-3), readout_s=6e-3)
    _, setup, start = _scene(n_markers=4, n_frames=30, timing=timing)
    setup = dataclasses.replace(setup, loss=Loss("none"))
    C = 5
    spec = shared.Shared(np.arange(C) > 0, np.ones(C, bool), np.arange(C) > 0,
                         np.tile(np.eye(6) * 1e-4, (C, 1, 1)))
    models, levels = np.full(4, "constant_velocity", object), np.full(4, 5.0)
    theta = np.random.default_rng(0).normal(0, 1e-3, spec.n)

    def cost(th, start=start):
        f = backends.FAST.fit(shared.applied(setup, spec, th), models, levels, start, covariances=False)
        return f.cost.sum(), f

    E0, f0 = cost(theta)
    lin = shared.linearise(shared.applied(setup, spec, theta), f0, spec, levels)
    warm = (f0.xyz, f0.velocity, None)
    for i in (0, 5, 12, 14):  # an offset, a readout, a pose's rotation and translation
        d = np.zeros(spec.n)
        d[i] = 1e-6
        Ep, Em = cost(theta + d, warm)[0], cost(theta - d, warm)[0]
        np.testing.assert_allclose(lin.g[i], (Ep - Em) / 2e-6, rtol=2e-3)
        np.testing.assert_allclose(lin.S[i, i], (Ep - 2 * E0 + Em) / 1e-12, rtol=0.05)


def test_shared_first_order_move_at_the_markers_own_noise_level():
    """Y = H_xx^-1 H_xt, the markers' first-order move per shared variable, equals the finite difference of their
    minimiser when the motion prior is that of the markers' levels (here 50, a flexible track): the prior sets how much
    of a change of the rig the trajectories absorb. Pose columns (Gauss-Newton is exact enough there: 0.4-1.2 %
    measured; with every level taken as 1, as the solve once did, 8 %)."""
    _, setup, start = _scene(n_markers=4, n_frames=30, timing=Timing(time_offsets_s=(0.0, 3.1e-3, 0.0, 0.0, 0.0)))
    setup = dataclasses.replace(setup, loss=Loss("none"))
    C = 5
    spec = shared.Shared(np.arange(C) > 0, np.zeros(C, bool), np.arange(C) > 0, np.tile(np.eye(6) * 1e-4, (C, 1, 1)))
    models, levels = np.full(4, "constant_velocity", object), np.full(4, 50.0)

    def minimiser(th, begin=start):
        return backends.FAST.fit(shared.applied(setup, spec, th), models, levels, begin, lm.TIGHT, covariances=False)

    theta = np.zeros(spec.n)
    f0 = minimiser(theta)
    lin = shared.linearise(shared.applied(setup, spec, theta), f0, spec, levels)
    warm = (f0.xyz, f0.velocity, None)
    for i in range(spec.columns["pose"][1], spec.n, 3):  # every pose's rotations and translations, in turn
        d = np.zeros(spec.n)
        d[i] = 1e-7
        moved = (minimiser(theta + d, warm).xyz - minimiser(theta - d, warm).xyz) / 2
        predicted = -lin.Y[..., :3, :] @ d
        assert np.linalg.norm(predicted - moved) < 0.03 * np.linalg.norm(moved), i


def test_segments_first_solve_starts_relaxed(monkeypatch):
    """The first solve with the segments starts from one with them SEGMENT_RELAX times softer. Scene: the last 80
    frames of the simulated flight, seed 2, where a single-view track end of the left wing (its markers chosen
    constant acceleration) lies nearer the far one of its segments' two depths in the segment-free solution: stiff
    segments from there hold it on that branch, 47 mm off on frames seen by two cameras, whose views are then
    rejected as outliers (measured: max error 47.5 mm, 12 rejected; relaxed 4.0 mm, none rejected)."""
    s = simulate_flight(np.random.default_rng(2), n_cameras=5)
    crop = lambda t: t[t.frame >= 80].assign(frame=lambda d: d.frame - 80).reset_index(drop=True)  # noqa: E731
    s = dataclasses.replace(s, observations=crop(s.observations), truth=crop(s.truth))
    dense = dense_observations(s)
    pre = checks.preflight(s, dense)
    truth = np.stack([s.truth[s.truth.marker == m].sort_values("frame")[["x", "y", "z"]].to_numpy()
                      for m in dense.markers], axis=1)
    worst, relaxed = {}, schedule.SEGMENT_RELAX
    for relax in (relaxed, 1.0):
        monkeypatch.setattr(schedule, "SEGMENT_RELAX", relax)
        est = schedule.run_smoother(pre.session, dense, pre.ideal, Options(progress=False))
        worst[relax] = np.linalg.norm(est.xyz_m - truth, axis=-1)[dense.n_views >= 2].max()
    assert worst[relaxed] < 0.01 and worst[1.0] > 0.02, worst


def test_threads_never_change_the_answer(monkeypatch):
    """The smoother on one thread and on three, its compiled loops split into many small parts and the motion models'
    noise searches side by side (batgraph.solver.threads): bit-identical positions, covariances and choices."""
    s = simulate_flight(np.random.default_rng(4), n_cameras=5, n_frames=40)
    dense = dense_observations(s)
    pre = checks.preflight(s, dense)
    monkeypatch.setattr(kernels, "MIN_PART_BLOCKS", 16)
    monkeypatch.setattr(kernels, "MIN_PART_ROWS", 16)
    answers = []
    for n in (1, 3):
        threads.set_threads(n)
        answers.append(schedule.run_smoother(pre.session, dense, pre.ideal, Options(progress=False)))
    threads.set_threads(threads._default())
    one, many = answers
    assert np.array_equal(one.xyz_m, many.xyz_m, equal_nan=True)
    assert np.array_equal(one.cov_m2, many.cov_m2, equal_nan=True)
    assert str(one.info) == str(many.info)
    assert threads.side_by_side([lambda: 1, lambda: 2, lambda: 3]) == [1, 2, 3]


def test_markers_seen_on_few_frames_take_their_segment_partners_level():
    """segments.partner_levels: an unset marker takes the least level of its set partners, along a chain of unset
    ones; one whose partners are all unset keeps its own."""
    level = np.array([2.0, 400.0, 0.01, 0.01, 0.01, 5.0, 0.01, np.nan])
    unset = level == 0.01
    pairs = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [0, 4], [5, 4], [6, 7]])  # marker 7: not estimated
    np.testing.assert_array_equal(fit.segments.partner_levels(level, unset, pairs),
                                  [2.0, 400.0, 400.0, 2.0, 2.0, 5.0, 0.01, np.nan])


def test_segment_lengths_start_from_the_frames_that_see_both_markers():
    """segments.initial_lengths: the median over the frames where a camera sees both markers, every frame where
    none does."""
    xyz = np.zeros((4, 3, 3))
    xyz[:, 1, 0] = [0.1, 0.1, 0.5, 0.5]  # marker 1 seen on frames 0-1 only, extrapolated off on 2-3
    xyz[:, 2, 0] = [0.2, 0.2, 0.2, 0.3]
    seen = np.array([[1, 1, 0], [1, 1, 0], [1, 0, 0], [1, 0, 0]], bool)
    np.testing.assert_allclose(fit.segments.initial_lengths(xyz, np.array([[0, 1], [0, 2]]), seen), [0.1, 0.2])


def test_segments_hold_a_wing_whose_markers_are_seen_on_few_frames():
    """A wingbeat scene (seed 1) whose left elbow, wrist and tip3 are labelled on every 6th frame, tip5 on frames
    30-31 only and tip4 there in one camera (never triangulated): sparse hand clicks. The segments must help, not
    hurt. Their evidence alone set tip5's motion noise at the search's stiffest level, a straight line through
    flapping points that the segment then bent the wrist to (measured: 30.5 mm worst on frames seen by two cameras,
    RMSE 1.75 mm against 1.43 without the segments; with the partners' levels 7.2 and 1.27 mm)."""
    s = wingbeat.simulate_wingbeat(np.random.default_rng(1))
    o = s.observations
    wing, tips = o.marker.isin(["L_elbow", "L_wrist", "L_tip3"]), o.marker.isin(["L_tip4", "L_tip5"])
    keep = ~(wing | tips) | (wing & (o.frame % 6 == 0)) | (tips & o.frame.isin([30, 31]))
    keep &= (o.marker != "L_tip4") | (o.camera == o.camera[o.marker == "L_tip4"].iloc[0])
    s = dataclasses.replace(s, observations=o[keep].reset_index(drop=True))
    dense = dense_observations(s)
    pre = checks.preflight(s, dense)
    truth = np.stack([s.truth[s.truth.marker == m].sort_values("frame")[["x", "y", "z"]].to_numpy()
                      for m in dense.markers], axis=1)
    err = {}
    for rigid in (True, False):
        session = pre.session if rigid else dataclasses.replace(pre.session, rigid=[])
        est = schedule.run_smoother(session, dense, pre.ideal, Options(progress=False))
        err[rigid] = np.linalg.norm(est.xyz_m - truth, axis=-1)[dense.n_views >= 2]
    rms = {k: float(np.sqrt(np.mean(e**2))) for k, e in err.items()}
    assert err[True].max() < 0.015 and rms[True] <= rms[False], (err[True].max(), rms)


def test_wingbeat_spectrum_of_a_track_seen_every_kth_frame_stays_finite():
    """A track triangulated on every 6th frame of 72 at 120 fps: the Lomb-Scargle terms whose sine or cosine
    vanishes on those frames (multiples of 10 Hz) have no power, not an infinite one that sets the flapping floor
    from a 20 Hz wingbeat that is not there."""
    F, fps = 72, 120.0
    t = np.arange(F) / fps
    xyz = np.full((F, 1, 3), np.nan)
    on = np.arange(F) % 6 == 0
    phase = 2 * np.pi * 8.0 * t[on]  # an 8 Hz wingbeat
    xyz[on, 0] = np.stack([0.05 * np.sin(phase), 0.01 * t[on], 1 + 0.02 * np.cos(phase)], axis=1)
    hz, power = motion.periodogram(xyz, fps)
    assert np.isfinite(power).all()
    assert abs(motion.wingbeat_peak(xyz, fps)[0] - 20.0) > 1.0
