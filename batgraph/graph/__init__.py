"""GTSAM factor graphs for marker trajectories: the batch smoother and the iSAM2 filter.

Modules, imports flowing one way (cost -> noise -> fast -> fast_filter; factors -> smoother, filter):
:mod:`.cost` (the cost's constants, motion parameters, robust losses, residuals and rejection rule, in
numpy), :mod:`.noise` (motion noise: given, the filter's causal q, the marginal-likelihood formulas),
:mod:`.fast` (the numpy smoother for a fixed rig, and the per-marker q search), :mod:`.fast_filter`
(the numpy filter), :mod:`.kernels` (their compiled inner loops, numba; imports only numpy and numba,
also used by batgraph.pixel_noise); the GTSAM reference: :mod:`.factors` (keys, projection / motion / prior factors,
camera variables), :mod:`.smoother` (batch Levenberg-Marquardt + marginals), :mod:`.filter` (iSAM2).
Only the last three import GTSAM; the fast paths hand over to them (imported then) when the rig has
camera pose covariances.

The cost (shared with any fast path), per estimated marker m and frame k of the session's range:
projection factors on ideal pixels whitened by the mapped pixel covariance (Huber / Cauchy / none);
a random-walk (paper eq. 3-5), constant-velocity (white-noise acceleration) or constant-acceleration
(white-noise jerk) motion factor between consecutive frames, the model per marker ("auto":
batgraph.graph.noise); weak gauge priors p[m, 0] ~ N(p_init, (10 m)^2), v[m, 0] ~ N(0, (10 m/s)^2),
a[m, 0] ~ N(0, (1000 m/s^2)^2). A marker is estimated when
it is triangulated (>= 2 views) on at least one frame. Nothing is imported here, so importing the
package does not load GTSAM.
"""
