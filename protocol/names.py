"""The parameter names (the layout's vocabulary), in a module that imports nothing, so that what only needs the names
(the commands' option help, ``hostlink calibrate --help``) does not load numpy with :mod:`protocol.param_table`,
which re-exports them."""

from __future__ import annotations

#: Distortion keys of a camera parameter file (docs/camera-model.md: radial k1 k2 k3, decentering p1 p2, thin prism
#: s1 s2), in the order of every parameter vector and table. THE list: every other module imports it.
DISTORTION_NAMES: tuple[str, ...] = ("k1", "k2", "k3", "p1", "p2", "s1", "s2")
#: Names of the estimable parameters, in the order of every parameter vector in the project (``--estimate`` names,
#: the sigma fields, the onboard estimate's values): focal length, principal point, then the distortion.
ESTIMATE_NAMES: tuple[str, ...] = ("f", "x0", "y0", *DISTORTION_NAMES)
