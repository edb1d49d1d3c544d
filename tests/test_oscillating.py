"""The oscillating motion model ([motion] model = "wingbeat"): constant velocity plus damped harmonics of the
wingbeat frequency (batgraph.graph.cost.oscillating_motion).

The fast solver's optimum, covariances, log det and Laplace evidence are checked against a dense
least-squares solve written here in another parameterisation of the same model: per frame a trend position
tau, a trend velocity v [m/s] and the harmonics (c_h, s_h), with the position tau + sum_h c_h; motion rows
from batgraph.motion's constant-velocity Q in physical units and each harmonic's rotation written out. The
two parameterisations differ by a map of determinant 1 (p = tau + sum c_h), so positions, covariances, cost,
log det and evidence must agree. Then the model's use: the frequency measured from tracks, the model chosen
per marker on a hold-out wingbeat scene, and the GTSAM smoother's refusal.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from test_fast import FPS, make_problem

from batgraph.errors import InputError
from batgraph.graph import cost as spec
from batgraph.graph import fast, noise, schedule
from batgraph.graph.smoother import run_smoother
from batgraph.motion import constant_velocity_Q, wingbeat_frequency
from batgraph.result import Options

HZ = 7.0  # wingbeat frequency of the tests' oscillation [Hz]
Q_TREND = 20.0  # the trend's q [m^2/s^3]
SIGMAS = np.array([0.003, 0.01, 0.002, np.nan])  # first-harmonic std per marker [m] (m3 is never triangulated)


@pytest.fixture(scope="module")
def scene():
    return make_problem()


def test_each_harmonic_is_stationary_with_its_std():
    """The harmonics' block of Q is (1 - rho^2) sigma_h^2 and their rotation keeps sigma_h^2 I stationary:
    rho R (sigma_h^2 I) rho R^T + Q_h = sigma_h^2 I; the trend block is batgraph.motion's Q in the scaled state."""
    dt, sigma = 1 / FPS, 0.004
    A, Q, P0 = spec.oscillating_motion(dt, spec.Oscillation(HZ, sigma), Q_TREND)
    assert A.shape == (18, 18) and Q.shape == (1, 18, 18) and P0.shape == (1, 18, 18)
    ax = np.arange(0, 18, 3)  # the x axis' values: p, u, c1, s1, c2, s2
    A1, Q1 = A[np.ix_(ax, ax)], Q[0][np.ix_(ax, ax)]
    for h in range(spec.OSC_HARMONICS):
        i = slice(2 + 2 * h, 4 + 2 * h)
        var = (sigma * spec.OSC_HARMONIC_RATIO**h) ** 2
        np.testing.assert_allclose(A1[i, i] @ (var * np.eye(2)) @ A1[i, i].T + Q1[i, i], var * np.eye(2),
                                   rtol=0, atol=1e-12 * var)
    S = np.diag([1.0, dt])
    np.testing.assert_allclose(Q1[1:2, 1:2], (S @ constant_velocity_Q(Q_TREND, dt)[np.ix_([0, 3], [0, 3])] @ S)[1:, 1:],
                               rtol=1e-12)
    assert np.all(np.linalg.eigvalsh(Q[0]) > 0)


def dense_oscillating(session, ideal, p_init, q, sigmas):
    """Least squares of the oscillating model in (tau, v [m/s], c_h, s_h) per frame, dense, Gauss-Newton
    with finite-difference projection Jacobians. Returns xyz (F, M, 3), cov (F, M, 3, 3), log det of the
    Hessian, cost, log det of the prior's information (the motion and first-frame rows alone)."""
    C, F, M = ideal.seen.shape
    dt = 1 / session.fps
    ms = np.flatnonzero(np.isfinite(p_init).all(axis=(0, 2)))
    H_ = spec.OSC_HARMONICS
    n_per = 3 * (2 + 2 * H_)  # tau, v, then c_h, s_h per harmonic, each a 3-vector
    n = len(ms) * F * n_per
    rho = math.exp(-dt * HZ / spec.OSC_COHERENCE_CYCLES)

    def idx(j, f, part, h=0):  # part: "tau", "v", "c", "s"
        base = (j * F + f) * n_per
        return base + {"tau": 0, "v": 3, "c": 6 + 6 * h, "s": 9 + 6 * h}[part]

    rows, b = [], []

    def add(coefs, target, weight):  # rows: weight (sum coef * var - target), coefs [(index, 3x3 matrix)]
        A = np.zeros((3, n))
        for i, mat in coefs:
            A[:, i:i + 3] += weight @ mat
        rows.append(A)
        b.append(weight @ target)

    I3 = np.eye(3)
    Wcv = np.linalg.inv(np.linalg.cholesky(constant_velocity_Q(q, dt)))  # (6, 6) on [tau; v] residuals
    for j, m in enumerate(ms):
        for f in range(F - 1):  # trend: [tau' - tau - v dt, v' - v] whitened jointly
            A = np.zeros((6, n))
            A[:3, idx(j, f + 1, "tau"):idx(j, f + 1, "tau") + 3] = I3
            A[:3, idx(j, f, "tau"):idx(j, f, "tau") + 3] = -I3
            A[:3, idx(j, f, "v"):idx(j, f, "v") + 3] = -dt * I3
            A[3:, idx(j, f + 1, "v"):idx(j, f + 1, "v") + 3] = I3
            A[3:, idx(j, f, "v"):idx(j, f, "v") + 3] = -I3
            rows.append(Wcv @ A)
            b.append(np.zeros(6))
            for h in range(H_):
                a = 2 * math.pi * HZ * (h + 1) * dt
                sd = sigmas[m] * spec.OSC_HARMONIC_RATIO**h
                w = I3 / (sd * math.sqrt(1 - rho * rho))
                add([(idx(j, f + 1, "c", h), I3), (idx(j, f, "c", h), -rho * math.cos(a) * I3),
                     (idx(j, f, "s", h), -rho * math.sin(a) * I3)], np.zeros(3), w)
                add([(idx(j, f + 1, "s", h), I3), (idx(j, f, "c", h), rho * math.sin(a) * I3),
                     (idx(j, f, "s", h), -rho * math.cos(a) * I3)], np.zeros(3), w)
        # first frame: the position tau + sum c_h ~ N(p_init[0], 10 m), v ~ N(0, 10 m/s), harmonics stationary
        add([(idx(j, 0, "tau"), I3)] + [(idx(j, 0, "c", h), I3) for h in range(H_)], p_init[0, m], I3 / 10.0)
        add([(idx(j, 0, "v"), I3)], np.zeros(3), I3 / 10.0)
        for h in range(H_):
            sd = sigmas[m] * spec.OSC_HARMONIC_RATIO**h
            add([(idx(j, 0, "c", h), I3)], np.zeros(3), I3 / sd)
            add([(idx(j, 0, "s", h), I3)], np.zeros(3), I3 / sd)
    Alin, blin = np.vstack(rows), np.concatenate(b)
    prior_logdet = np.linalg.slogdet(Alin.T @ Alin)[1]
    obs = [(c, f, m) for c in range(C) for f in range(F) for m in ms if ideal.seen[c, f, m]]
    Linv = {o: np.linalg.inv(np.linalg.cholesky(ideal.cov_px2[o])) for o in obs}

    def position(z, j, f):
        return z[idx(j, f, "tau"):idx(j, f, "tau") + 3] + sum(z[idx(j, f, "c", h):idx(j, f, "c", h) + 3]
                                                             for h in range(H_))

    def evaluate(z):
        r = Alin @ z - blin
        cost, H, g = 0.5 * r @ r, Alin.T @ Alin, Alin.T @ r
        for (c, f, m) in obs:
            j = int(np.flatnonzero(ms == m)[0])
            p = position(z, j, f)
            res = Linv[(c, f, m)] @ (session.rig[c].project(p, distort=False) - ideal.uv_px[c, f, m])
            cost += 0.5 * res @ res
            J = np.zeros((2, 3))
            for a in range(3):
                e = np.zeros(3)
                e[a] = 1e-6
                J[:, a] = (session.rig[c].project(p + e, distort=False)
                           - session.rig[c].project(p - e, distort=False)) / 2e-6
            Jw = Linv[(c, f, m)] @ J
            cols = [idx(j, f, "tau")] + [idx(j, f, "c", h) for h in range(H_)]
            for i0 in cols:
                g[i0:i0 + 3] += Jw.T @ res
                for i1 in cols:
                    H[i0:i0 + 3, i1:i1 + 3] += Jw.T @ Jw
        return cost, H, g

    z = np.zeros(n)
    for j, m in enumerate(ms):
        for f in range(F):
            z[idx(j, f, "tau"):idx(j, f, "tau") + 3] = p_init[f, m]
    for _ in range(50):
        cost, H, g = evaluate(z)
        dz = np.linalg.solve(H, -g)
        z = z + dz
        if np.abs(dz).max() < 1e-12:
            break
    cost, H, _ = evaluate(z)
    Sigma = np.linalg.inv(H)
    xyz, cov = np.full((F, M, 3), np.nan), np.full((F, M, 3, 3), np.nan)
    for j, m in enumerate(ms):
        for f in range(F):
            cols = [idx(j, f, "tau")] + [idx(j, f, "c", h) for h in range(H_)]
            T = np.zeros((3, n))
            for i0 in cols:
                T[:, i0:i0 + 3] = I3
            xyz[f, m], cov[f, m] = position(z, j, f), T @ Sigma @ T.T
    return xyz, cov, np.linalg.slogdet(H)[1], cost, prior_logdet


def test_fast_equals_dense_least_squares(scene):
    """Positions to 1e-6 m, covariances to 1e-6 relative, cost, log det and the Laplace evidence (noise's
    formula with oscillating_logdets against the dense prior's own log det) to 1e-6."""
    session, dense, ideal, p_init = scene
    F = p_init.shape[0]
    osc = spec.Oscillation(HZ, SIGMAS)
    xyz, cov, info = fast.solve_fast(session, ideal, p_init, spec.OSCILLATING, Q_TREND, FPS, "none", 2.0,
                                     oscillation=osc)
    xyz_ref, cov_ref, logdet_ref, cost_ref, prior_ref = dense_oscillating(session, ideal, p_init, Q_TREND, SIGMAS)
    assert np.isnan(xyz[:, 3]).all() and np.isfinite(xyz[:, :3]).all()
    np.testing.assert_allclose(xyz[:, :3], xyz_ref[:, :3], rtol=0, atol=1e-6)
    scale = np.abs(cov_ref[:, :3]).max(axis=(-1, -2), keepdims=True)
    assert np.max(np.abs(cov[:, :3] - cov_ref[:, :3]) / scale) < 1e-6
    assert abs(info["cost"] - cost_ref) < 1e-9 * cost_ref
    assert abs(info["logdet"] - logdet_ref) < 1e-6
    ev = noise.laplace_log_evidence(info["cost_per_marker"][:3], info["logdet_per_marker"][:3], Q_TREND, 1 / FPS,
                                    F - 1, model=spec.OSCILLATING, oscillation=osc.of(np.arange(3)))
    assert abs(ev.sum() - (-cost_ref - 0.5 * logdet_ref + 0.5 * prior_ref)) < 1e-6
    assert info["converged"][:3].all()


def test_solve_levels_equals_solve_fast(scene):
    """The search's batch over (q, sigma_m) candidates gives each candidate solve_fast's answer alone."""
    session, dense, ideal, p_init = scene
    M = p_init.shape[1]
    levels = np.array([[Q_TREND] * M, [0.5] * M, np.geomspace(0.1, 300.0, M)])
    sig = np.array([[0.004] * M, [0.02] * M, np.geomspace(1e-4, 0.05, M)])
    batch = fast.solve_levels(session.rig, ideal, p_init, spec.OSCILLATING, levels, FPS, "huber", 2.0,
                              oscillation=spec.Oscillation(HZ, sig))
    for k in range(len(levels)):
        xyz, _, info = fast.solve_fast(session, ideal, p_init, spec.OSCILLATING, levels[k], FPS, "huber", 2.0,
                                       covariances=False, oscillation=spec.Oscillation(HZ, sig[k]))
        np.testing.assert_allclose(batch["position"][k], xyz, rtol=0, atol=1e-8)
        np.testing.assert_allclose(batch["velocity"][k], info["velocity"], rtol=0, atol=1e-6)
        np.testing.assert_allclose(batch["cost"][k], info["cost_per_marker"], rtol=1e-8)
        np.testing.assert_allclose(batch["logdet"][k], info["logdet_per_marker"], rtol=1e-8)


def test_velocity_includes_the_oscillation(scene):
    """The reported velocity is the trend's plus the harmonics' d c_h / dt: on a smooth solution it matches
    the positions' central differences (to the discretisation of a 7 Hz motion at 100 fps). Measured: 0.053 of
    the velocity's RMS; the trend's velocity alone is off by 0.13."""
    session, dense, ideal, p_init = scene
    xyz, _, info = fast.solve_fast(session, ideal, p_init, spec.OSCILLATING, Q_TREND, FPS, "none", 2.0,
                                   oscillation=spec.Oscillation(HZ, SIGMAS))
    diff = (xyz[2:, :3] - xyz[:-2, :3]) * FPS / 2
    v = info["velocity"][1:-1, :3]
    assert np.sqrt(np.mean((diff - v) ** 2)) < 0.08 * np.sqrt(np.mean(v**2))


def test_wingbeat_frequency_from_tracks():
    """A 9 Hz oscillation on a curved path with noise and gaps is found to 1 / (8 take lengths); no tracks, a
    take too short for two cycles of anything, and a slow sway without a wingbeat (a maximum at the band's
    edge) give None; that sway with a 9 Hz oscillation added gives 9 Hz."""
    rng = np.random.default_rng(0)
    fps, F = 120.0, 96
    t = np.arange(F) / fps
    xyz = np.zeros((F, 3, 3))
    for m in range(3):
        xyz[:, m, 0] = 4.0 * t + 0.5 * t * t  # flight path and a turn
        xyz[:, m, 2] = (0.003 + 0.03 * m) * np.sin(2 * np.pi * 9.0 * t + m)
    xyz += rng.normal(0, 0.002, xyz.shape)
    xyz[20:35, 2] = np.nan  # a wing hides the marker for a while
    found = wingbeat_frequency(xyz, fps)
    assert abs(found - 9.0) < fps / F / 8
    assert wingbeat_frequency(np.full((F, 2, 3), np.nan), fps) is None
    assert wingbeat_frequency(xyz[:7], fps) is None  # 7 frames cannot hold two cycles of anything below fps / 4
    slow = np.zeros((F, 4, 3))  # a 0.8 Hz sway and no wingbeat: the spectrum peaks at the band's lower end
    slow[:, :, 0] = 4.0 * t[:, None]
    slow[:, :, 1] = 0.05 * np.sin(2 * np.pi * 0.8 * t[:, None] + rng.uniform(0, 6, 4))
    slow += rng.normal(0, 0.001, slow.shape)
    assert wingbeat_frequency(slow, fps) is None
    slow[:, :, 2] = 0.01 * np.sin(2 * np.pi * 9.0 * t[:, None])  # the same with a wingbeat
    assert abs(wingbeat_frequency(slow, fps) - 9.0) < fps / F / 8


def test_periodogram_is_scipys_lomb_scargle(monkeypatch):
    """motion.periodogram (every track at once) equals scipy.signal.lombscargle summed over the tracks, each
    detrended by a quadratic over its own frames, on tracks with gaps of every kind (a block, every third
    frame, half the frames at random, a track too short to count), to 1e-10 relative; computed in chunks of
    frequencies, the same numbers."""
    from scipy.signal import lombscargle

    from batgraph import motion
    from batgraph.motion import WINGBEAT_MIN_FRAMES, periodogram

    rng = np.random.default_rng(0)
    fps, F, M = 120.0, 96, 5
    t = np.arange(F) / fps
    wave = 0.01 * np.sin(2 * np.pi * 9 * t)[:, None, None] * rng.uniform(0.2, 1, (1, M, 3))
    xyz = rng.normal(0, 0.002, (F, M, 3)) + wave
    xyz[:, :, 0] += 4 * t[:, None]
    xyz[20:40, 1] = np.nan
    xyz[::3, 2, 1] = np.nan
    xyz[rng.uniform(size=F) < 0.5, 3, 2] = np.nan
    xyz[5:, 4] = np.nan
    hz, power = periodogram(xyz, fps)
    ref = np.zeros(len(hz))
    for track in np.moveaxis(xyz, 0, -1).reshape(-1, F):
        ok = np.isfinite(track)
        if ok.sum() < WINGBEAT_MIN_FRAMES:
            continue
        tt = t[ok] - t[ok].mean()
        ref += lombscargle(tt, track[ok] - np.polyval(np.polyfit(tt, track[ok], 2), tt), 2 * np.pi * hz)
    np.testing.assert_allclose(power, ref, rtol=1e-10)
    monkeypatch.setattr(motion, "PERIODOGRAM_CHUNK", 7)  # the frequencies in chunks that do not divide them
    np.testing.assert_allclose(motion.periodogram(xyz, fps)[1], power, rtol=1e-12)


@pytest.fixture(scope="module")
def dorsal():
    """The hold-out wingbeat scene whose body markers bob with the wingbeat (4 cameras, dorsal markers)."""
    from batgraph.wingbeat import simulate_wingbeat

    return simulate_wingbeat(np.random.default_rng(1), flight="straight", n_cameras=4, fps=120.0, n_frames=96,
                             flap_hz=8.0, pixel_sigma_px=2.0, marker_side="dorsal")


def test_wingbeat_model_on_a_bobbing_body(dorsal, monkeypatch):
    """On the dorsal scene, constant velocity's evidence puts the body's markers (which bob +-3 mm and pitch
    +-3 deg at 8 Hz) at the search's floor, q = 0.01, and their 95 % ellipsoids cover their truth on fewer than
    70 % of observed frames (measured 48 / 37 / 55 / 58 %); the flapping floor (noise.flapping_q_floor: q >= 1.9
    at 8 Hz, the heave of a lift swinging by one body weight) raises them, covering >= 90 % with no larger RMSE
    (measured: 99 / 100 / 97 / 100 %, RMSE of observed points 5.34 -> 5.29 mm; with the 1 mm floor before the
    eighteenth session 69 / 65 / 80 / 81 %); its info notes that
    the tracks move periodically at 8 Hz, which it does not model. "wingbeat" measures the frequency (8 Hz to
    the spectrum's 1/16 bin), gives them the oscillation, and covers >= 90 % (measured: 97 / 97 / 100 / 100 %),
    with every observed point's RMSE lower."""
    from batgraph import evaluate
    from batgraph.pipeline import run_methods

    body = ["head", "rump", "R_shoulder", "L_shoulder"]
    out = {}
    for run, model, swing in (("no floor", "constant_velocity", 0.0),
                              ("constant_velocity", "constant_velocity", noise.FLAPPING_LIFT_SWING),
                              ("wingbeat", "wingbeat", noise.FLAPPING_LIFT_SWING)):
        monkeypatch.setattr(noise, "FLAPPING_LIFT_SWING", swing)
        res = run_methods(dorsal, ["smoother"], Options(progress=False, motion_model=model))
        e = evaluate.point_errors(res.trajectories, dorsal.truth)
        obs = e[e.status == "observed"]
        out[run] = (obs.groupby("marker").mahal2.apply(lambda x: np.mean(x < 7.8147))[body],
                    np.sqrt(np.mean(obs.err_m**2)), res.estimates["smoother"].info, res.summary["warnings"])
    bare, cv, wb = out["no floor"], out["constant_velocity"], out["wingbeat"]
    assert (bare[0] < 0.7).all() and all(bare[2]["accel_psd_m2_s3"][m] < 0.011 for m in body)
    assert (wb[0] >= 0.9).all()
    # the floor: the body's markers at q of a 3.9 mm heave at the measured frequency, covered
    floor = noise.flapping_q_floor(cv[2]["periodic_motion_hz"])
    assert 1.8 < floor < 2.0 and set(cv[2]["accel_psd_floor"]["markers"]) >= set(body)
    assert cv[2]["accel_psd_floor"]["flapping_heave_m"] == pytest.approx(9.81 / (2 * np.pi * 7.97) ** 2, rel=0.01)
    assert all(cv[2]["accel_psd_m2_s3"][m] == floor for m in body) and "accel_psd_floor" not in bare[2]
    assert (cv[0] >= 0.9).all() and cv[1] <= bare[1] * 1.01
    # constant velocity notes that the tracks move periodically (its info); a flapping animal is no warning
    assert abs(cv[2]["periodic_motion_hz"] - 8.0) < 120.0 / 96 / 8 and cv[2]["wingbeat_advice"] not in cv[3]
    assert "wingbeat_advice" not in wb[2] and not any("periodically" in w for w in wb[3])
    assert wb[1] < cv[1]
    info = wb[2]
    assert info["wingbeat_hz_source"] == "measured" and abs(info["wingbeat_hz"] - 8.0) < 120.0 / 96 / 8
    assert all(info["motion_model_per_marker"][m] == "oscillating" for m in body)
    assert set(info["oscillation_sigma_m"]) >= set(body)


def test_the_surrogate_screened_grid_chooses_what_the_whole_grid_does(dorsal, monkeypatch):
    """The oscillating model's noise search solves only the fast.GRID_TOP grid points the evidence's surrogate
    at the start scores best (of 5 q x 4 sigma_m); on the dorsal scene every marker gets the trend q and
    sigma_m that solving the whole grid gives (measured: the same levels, evidence to 2e-7 nats; asserted within the
    search's tolerance 0.05 decade and 0.05 nats). Solving the 4 the surrogate scores worst instead changes
    them (so the check can fail)."""
    from batgraph import checks
    from batgraph.session import dense_observations
    from batgraph.triangulate import dlt_points

    dense = dense_observations(dorsal)
    pre = checks.preflight(dorsal, dense)
    tri = dlt_points(pre.session.rig, pre.ideal)
    p_init, v_init, est = spec.initial_track(tri, dorsal.fps)
    markers = np.flatnonzero(est)

    def search():
        level, info = fast.choose_noise_per_marker(pre.session.rig, pre.ideal, p_init, v_init, markers, dorsal.fps,
                                                   "huber", 2.0, model=spec.OSCILLATING, oscillation_hz=8.0)
        return np.log10(level[markers]), np.log10(info["sigma_m"][markers]), info["log_evidence"][markers]

    screened = search()
    monkeypatch.setattr(fast, "GRID_TOP", 100)
    whole = search()
    print("screened", np.round(screened[0], 3), np.round(screened[1], 3))
    print("whole   ", np.round(whole[0], 3), np.round(whole[1], 3))
    for a, b in zip(screened[:2], whole[:2], strict=True):
        np.testing.assert_allclose(a, b, atol=0.05)
    print("max |evidence difference|", np.abs(screened[2] - whole[2]).max())
    np.testing.assert_allclose(screened[2], whole[2], atol=0.05)
    monkeypatch.setattr(fast, "GRID_TOP", 4)
    best_rows = fast._best_rows
    monkeypatch.setattr(fast, "_best_rows", lambda scores, n: best_rows(-scores, n))  # the worst 4
    worst = search()
    assert np.abs(worst[2] - whole[2]).max() > 1.0


def test_wingbeat_model_without_a_wingbeat_says_so():
    """A glide (no flapping; the hold-out generator's seed 2) has no wingbeat to find: "wingbeat" runs every
    marker with constant velocity, the same answer as constant velocity itself, and summary.json's warnings
    say why, in one line."""
    from batgraph.pipeline import run_methods
    from batgraph.wingbeat import simulate_wingbeat

    glide = simulate_wingbeat(np.random.default_rng(2), flight="glide", n_cameras=5, fps=60.0, n_frames=60,
                              pixel_sigma_px=2.0)
    out = {model: run_methods(glide, ["smoother"], Options(progress=False, motion_model=model))
           for model in ("wingbeat", "constant_velocity")}
    info = out["wingbeat"].estimates["smoother"].info
    assert info["wingbeat_hz"] is None and info["wingbeat_left_out"] == schedule.NO_WINGBEAT
    assert set(info["motion_model_per_marker"].values()) == {"constant_velocity"}
    (line,) = out["wingbeat"].summary["warnings"]  # one line; the note is its details
    assert out["wingbeat"].summary["warning_details"][line] == schedule.NO_WINGBEAT
    assert out["constant_velocity"].summary["warnings"] == []
    assert "wingbeat_advice" not in out["constant_velocity"].estimates["smoother"].info  # no periodic motion
    a, b = (out[m].estimates["smoother"] for m in ("wingbeat", "constant_velocity"))
    np.testing.assert_array_equal(a.xyz_m, b.xyz_m)
    np.testing.assert_array_equal(a.cov_m2, b.cov_m2)


def test_gtsam_smoother_refuses_the_wingbeat_model(scene):
    """One line naming the model, not a wrong answer (a given q would make it constant velocity, so none here)."""
    session, dense, ideal, p_init = scene
    session = dataclasses.replace(session, motion=dataclasses.replace(session.motion, accel_psd_m2_s3=None))
    with pytest.raises(InputError, match="wingbeat"):
        run_smoother(session, dense, ideal, Options(progress=False, motion_model="wingbeat"))
