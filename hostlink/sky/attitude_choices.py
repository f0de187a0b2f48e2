"""The attitude solver's option values (choices and defaults), in a module that imports nothing, so that the
commands' option parsers (``hostlink attitude --help``) do not load numpy with :mod:`hostlink.sky.attitude`."""

from __future__ import annotations

REFRACTION_MODES = ("reference", "observed", "none")
REFRACTION_MODELS = ("atan", "seed001")
PRECISIONS = ("float64", "float32")
#: Default residual above which a star is dropped as misidentified [arcsec]: far above noise (a few arcsec) and
#: uncorrected differential refraction across a field (< 20" at 75 deg), far below a wrong identity (degrees).
DEFAULT_REJECT_ARCSEC = 60.0
