"""batgraph: 3D marker trajectories from multi-camera 2D tracks, with honest uncertainty.

A GTSAM factor graph (every marker on every frame a Point3, random-walk or constant-velocity motion
factors, projection factors per observation) solved as a batch smoother and as an iSAM2 filter,
beside the Bender et al. EKF/UKF and per-frame triangulation baselines.
"""

__version__ = "0.1.0"
