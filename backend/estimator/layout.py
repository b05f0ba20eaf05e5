"""The layout of the filter's state vector and of one observation's rows (defined once).

The error state is ``[xi (6), b_g (3), theta_1 (3), ..., theta_n (3)]``: the pose (6: translation
then rotation, Barfoot's ``[rho, theta]``), the gyro bias, and 3 parameters per landmark in the
state, in slot order; ``P`` is one dense covariance over it. Where the filter estimates the stereo
pair's residual disparity offset (O1 of ``backend.estimator.offset``), its row :data:`OFFSET` follows
the bias and the core has ``CORE + 1`` rows. The inertial state puts velocity and
accelerometer bias before the landmarks (``backend.estimator.inertial.CORE_INERTIAL`` = 15 rows):
the number of rows before the first landmark is the state's ``core``, and landmark slot ``s``
owns rows :func:`landmark_row` (core, s) .. + 2 in every module. Each stereo observation enters
the update as :data:`ROWS` rows ``[uL, (vL + vR)/sqrt 2, uR]`` (U1, ``backend.estimator.update``).
"""

import numpy as np

from ..compiled import jit

POSE = slice(0, 6)  # pose error
BIAS = slice(6, 9)  # gyro bias
CORE = 9  # pose + gyro bias: the landmark slots start here, 3 rows each
OFFSET = 9  # the residual disparity offset (px), where estimated (the core is then CORE + 1 rows)
LEVER_ROWS = 3  # the residual lever arm (m, IMU frame), where carried: after the bias and the offset (V1)
ROWS = 3  # rows per observation in the update (U1)
SQRT_HALF = float(np.sqrt(0.5))


@jit
def landmark_row(core, slot):
    """The first row of landmark ``slot`` in a state of ``core`` rows before the landmarks."""
    return core + 3 * slot


def state_dimension(core: int, num_landmarks: int) -> int:
    """Rows of P: ``core`` and 3 per landmark."""
    return core + 3 * num_landmarks


def landmark_rows(core: int, slots: np.ndarray) -> np.ndarray:
    """(k,3) rows of P of the landmarks ``slots`` (k,)."""
    return core + 3 * np.asarray(slots, dtype=np.int64)[:, None] + np.arange(3)
