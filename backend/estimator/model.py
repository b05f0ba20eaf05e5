"""The error model: how the filter parametrizes the error of its estimate (one class per model).

The filter's mean is the pose mu = world_T_imu, the gyro bias and the landmark parameters; its
covariance P is over an error state whose meaning the model defines, and with it the
prediction of P (a ``Transition`` that ``StateHelper.propagate`` applies), the observation
Jacobians, the Jacobians of a new landmark (``StateHelper.augment`` adds it), the correction of
the mean by an update dx, and the covariances reported in the world and body frames. A model
moves the mean; it never writes P (``backend.estimator.state_helper``):

- :class:`~vislam.backend.estimator.invariant.InvariantModel`: the right-invariant error of pose
  and world-xyz landmarks (I1-I7; the default);
- :class:`~vislam.backend.estimator.body.BodyModel`: the course's right perturbation
  mu exp(xi^) (B1-B4), for xyz or inverse-depth landmarks.

When the poses are held fixed (mapping) only the mean moves in the prediction, by (P1): the
prediction returns no transition.
"""

from __future__ import annotations

import abc

import numpy as np

from ..config import Parametrization
from ..geometry import se3
from ..geometry.camera import StereoCamera
from .state import FilterState
from .state_helper import NewLandmarks, Transition
from .update import Innovation


class ErrorModel(abc.ABC):
    """One parametrization of the filter's error (module docstring).

    ``estimate_pose``: the pose is part of the state (slam), else held fixed (mapping);
    ``estimate_bias``: the gyro bias is.
    """

    def __init__(self, camera: StereoCamera, imu_T_cam: np.ndarray, parametrization: Parametrization,
                 estimate_pose: bool, estimate_bias: bool) -> None:
        self.camera = camera
        self.imu_T_cam = np.array(imu_T_cam, dtype=float)
        self.cam_T_imu = se3.inverse(self.imu_T_cam)
        self.parametrization = Parametrization(parametrization)
        self.estimate_pose = estimate_pose
        self.estimate_bias = estimate_bias

    #: per-landmark arrays of FilterState this model reads besides ``theta``
    per_landmark: tuple[str, ...] = ()

    @abc.abstractmethod
    def predict(self, state: FilterState, twist: np.ndarray, q: np.ndarray, dt: float,
                bias_walk_var: float) -> Transition | None:
        """Move the mean by the body twist ``twist`` (6,) = tau u; returns P's prediction, with twist
        noise sigmas times tau ``q`` (6,) and the bias walk's variance per step (None: poses held)."""

    @abc.abstractmethod
    def innovation(self, state: FilterState, slots: np.ndarray, pixels: np.ndarray, pixel_var: float) -> Innovation:
        """The prior innovation (3-row form, U1) of the observations ``pixels`` (k,4) of landmarks ``slots``."""

    @abc.abstractmethod
    def initialize(self, state: FilterState, pixels: np.ndarray, sigma: float) -> NewLandmarks:
        """New landmarks from stereo pixels (n,4): their parameters and Jacobians (A1).
        ``sigma`` > 0: start xyz points at the expected triangulation under that pixel noise (S3)."""

    @abc.abstractmethod
    def correct(self, state: FilterState, dx: np.ndarray) -> None:
        """Apply the update dx (D,) of the error state to the mean."""

    @abc.abstractmethod
    def world_landmarks(self, state: FilterState, slots: np.ndarray):
        """(positions (k,3), covariances (k,3,3), finite (k,) bool) of landmarks ``slots`` in the world frame."""

    @abc.abstractmethod
    def pose_covariance(self, state: FilterState) -> np.ndarray:
        """6x6 covariance of the right perturbation world_T_imu = mu exp(xi^)."""

    #: the model carries landmarks through a frozen step (:meth:`predict_frozen`); else the filter ends their tracks
    freezes: bool = False

    def predict_frozen(self, state: FilterState, twist: np.ndarray, q: np.ndarray, dt: float, bias_walk_var: float,
                       imu_weight: np.ndarray | None = None) -> Transition | None:
        """A step whose frame repeats the previous one: the pose moves by ``twist`` as in :meth:`predict`
        while the landmarks keep their coordinates in the body frame (the content froze: the world
        moved with the camera); returns P's prediction. ``imu_weight`` (6,): the IMU's share of each
        axis of ``twist`` where it fuses another prediction. Only models with ``freezes`` implement it."""
        raise NotImplementedError(f"{type(self).__name__} does not carry landmarks through a frozen step")

    @staticmethod
    def predict_mean_only(state: FilterState, step: np.ndarray) -> None:
        """(P1) mu <- mu step for step = exp(tau u^)."""
        state.mu = state.mu @ step
