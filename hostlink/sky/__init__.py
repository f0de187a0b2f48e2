"""The sky side of the host (docs/architecture.md ``hostlink/sky``): the Hipparcos catalogue, the geocentric apparent
place of its stars at a frame's time (pyerfa), THE reference-direction service (``references``: session rows ->
reference unit vectors, with a site's diurnal aberration and refraction), the attitude of a session's frames
(``attitude``), the local geometry of a ground site and ERFA's refraction (the host's truth that the onboard float32
code is tested against), and the real-sky sensor simulator behind ``hostlink simulate``.
"""
