"""Host side of the star-sensor companion (docs/architecture.md): links, emulated sensors, the sky simulator, batch
ground calibration, the CLI and reports. float64 throughout; may import ``onboard`` and ``protocol``.

The public Python API is :mod:`hostlink.api` (docs/api.md): ``from hostlink import api``."""
