"""The attitude's Cramer-Rao covariance and the angle between two attitudes, for the tests: they live in the package
(``hostlink.calibration.crb``, exposed through ``hostlink.api``); this module keeps the tests' short import."""

from hostlink.calibration.crb import attitude_covariance, rotation_angle_rad  # noqa: F401
