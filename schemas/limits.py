"""Physical ranges of the wire contract: the outer bounds every frame is checked against when it is decoded.

A value outside them is physically meaningless whatever the robot; a frame holding one is rejected with the reason
``range`` (``nonfinite`` for NaN or infinity). A worker may hold tighter limits in its configuration (the
localizer's ``max_speed``, the detector's ``max_image_pixels``...), each bounded by the constant here and checked at
its boundary with a counted reason. The table of every field's range: docs/wire.md.
"""

from __future__ import annotations

MAX_COORDINATE = 1e7  # m: |x|, |y|, |z| of a position in a world frame (a UTM northing is below 1e7 m)
MAX_MOUNT_OFFSET = 100.0  # m: |translation| of a camera on its body (T_body_cam)
MAX_ANGLE = 1e4  # rad: |theta| of a planar pose (any number of turns; wrapped where it is used)
MAX_SPEED = 100.0  # m/s: |v|, |v_lateral| of an odometry frame
MAX_TURN_RATE = 50.0  # rad/s: |omega| of an odometry frame
MAX_ODOMETRY_DT = 3600.0  # s: the longest interval one odometry frame may cover
MAX_VARIANCE = 1e14  # |entry| of a covariance matrix (the square of MAX_COORDINATE)
PSD_TOLERANCE = 1e-9  # a covariance's eigenvalues may be this far below 0, relative to its largest entry (rounding)
MAX_OBJECT_SIZE = 1e4  # m: an object's extent along each axis
MAX_FOCAL = 1e6  # px: focal lengths and |principal point| of a pinhole camera
MAX_DISTORTION = 1e4  # |coefficient| of an OpenCV distortion model
MAX_CLOCK_AHEAD = 86400.0  # s: how far a frame's stamp may run ahead of its receiver's clock (clocks not synchronised,
# time zones; services.frames.check_clock)
SCORE_TOLERANCE = 1e-6  # a detector score may exceed 1 by this much (float rounding of value * scale)
