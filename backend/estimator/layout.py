"""The layout of the filter's state vector and of one observation's rows (defined once).

The error state is ``[xi (6), b_g (3), theta_1 (3), ..., theta_n (3)]``: the pose (6: translation
then rotation, Barfoot's ``[rho, theta]``), the gyro bias, and 3 parameters per landmark in the
state, in slot order; ``P`` is one dense covariance over it. Each stereo observation enters the
update as :data:`ROWS` rows ``[uL, (vL + vR)/sqrt 2, uR]`` (U1, ``backend.estimator.update``).
"""

import numpy as np

POSE = slice(0, 6)  # pose error
BIAS = slice(6, 9)  # gyro bias
CORE = 9  # pose + gyro bias: the landmark slots start here, 3 rows each
ROWS = 3  # rows per observation in the update (U1)
SQRT_HALF = float(np.sqrt(0.5))

