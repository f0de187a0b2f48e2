"""Host side of the star-sensor companion (ARCHITECTURE.md): links, emulated sensors, the sky simulator, batch
ground calibration, the CLI and reports. float64 throughout; may import ``onboard`` and ``protocol``."""
