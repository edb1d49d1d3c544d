"""Camera geometry as pure functions on arrays: the one place where each convention is converted.

Modules: :mod:`.pose` (rotations, cam_from_world <-> world_from_cam, similarities, GTSAM's and COLMAP's pose
tangents), :mod:`.distortion` (OpenCV's 5-parameter lens, its Jacobian and inverse), :mod:`.pinhole`
(projection by K, R, t or P = K [R | t], and its Jacobians), :mod:`.triangulation` (linear triangulation),
:mod:`.dlt` (DLT coefficients <-> K, R, t; pixel origins), :mod:`.gauge` (a rig's 7 gauge freedoms).
Conventions, stated once for the whole project:
* Poses are **cam_from_world**: ``xyz_cam = R @ xyz_world + t``, ``R = Rodrigues(rvec)`` (aniposelib / OpenCV /
  COLMAP). GTSAM's ``Pose3`` of a camera is world_from_cam, tangent ``[omega (rad), v (m)]`` perturbed on the
  right (``T exp(xi)``); COLMAP's pose tangent is Ceres' ``[half-angle quaternion increment, dt]``.
* Camera axes x right, y down, z forward. Pixels follow OpenCV: (0, 0) is the centre of the top-left pixel.
* Raw pixels are image coordinates; "ideal" pixels an undistorted pinhole's with the same K:
  ``uv_ideal = K @ [x/z, y/z, 1]``; skew ``K[0, 1]`` is honoured everywhere. Lens: OpenCV (k1, k2, p1, p2, k3).
This package imports numpy, scipy and OpenCV only: no GTSAM, no pycolmap, no files, no estimation.
"""
