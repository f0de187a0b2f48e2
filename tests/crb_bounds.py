"""The Cramer-Rao bound and the validation residual, for the tests: they live in the package
(``hostlink.calibration.crb``, exposed through ``hostlink.api``); this module keeps the tests' short import."""

from hostlink.calibration.crb import (  # noqa: F401
    GRID_SIDE,
    crb_validation_px,
    fisher_information,
    grid_points,
    interstar_frame_information,
    validation_jacobian,
    validation_residual_from_directions_px,
    validation_residual_px,
)
