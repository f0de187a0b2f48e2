"""Random star fields through a known camera, for the tests: they live in the package
(``hostlink.calibration.synthetic``, exposed through ``hostlink.api``); this module keeps the tests' short import."""

from hostlink.calibration.synthetic import SyntheticSession, synthetic_session  # noqa: F401
