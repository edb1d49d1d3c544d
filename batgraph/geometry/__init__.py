"""Camera geometry as pure functions on arrays: the one place where each convention is converted.

Modules (import them directly, e.g. ``from batgraph.geometry import pinhole``):

* :mod:`.pose`: rotation vectors <-> matrices, cam_from_world <-> world_from_cam, the similarity
  transform of a pose, GTSAM's Pose3 tangent and COLMAP's pose tangent, rotation angles.
* :mod:`.distortion`: OpenCV's 5-parameter lens model on normalised coordinates, its Jacobian and
  inverse.
* :mod:`.pinhole`: projection by K, R, t or by P = K [R | t] (ideal or raw pixels) and its
  Jacobians with respect to the point and to a world_from_cam pose perturbation.
* ``dlt``: DLT coefficients <-> K, R, t and pixel origins.

Conventions, stated once for the whole project:

* Poses are **cam_from_world**: ``xyz_cam = R @ xyz_world + t``, ``R = Rodrigues(rvec)`` (the
  aniposelib / OpenCV / COLMAP convention). GTSAM's ``Pose3`` of a camera is world_from_cam
  (:func:`.pose.world_from_cam` converts); its tangent is ``[omega (rad), v (m)]``, perturbed on the
  right (``T exp(xi)``). COLMAP's pose tangent is Ceres' ``[half-angle quaternion increment, dt]``
  of cam_from_world (:func:`.pose.pose_cov_gtsam_from_colmap` converts a covariance).
* Camera axes: x right, y down, z forward (optical axis).
* Pixels follow OpenCV: (0, 0) is the centre of the top-left pixel, u to the right, v downward.
* "Distorted" (raw) pixels are image coordinates; "ideal" pixels are what an undistorted pinhole with
  the same K would see: ``uv_ideal = K @ [x/z, y/z, 1]``. Skew ``K[0, 1]`` is honoured everywhere.
* Distortion: OpenCV (k1, k2, p1, p2, k3) on normalised coordinates.

This package imports numpy, scipy and OpenCV only: no GTSAM, no pycolmap, no file formats, no
estimation (the fast solvers use it without loading GTSAM).
"""
