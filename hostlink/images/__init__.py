"""The image side of the host (docs/architecture.md ``hostlink/images``): THE image reader (``read``: FITS, TIFF, PNG
into one float64 array with the exposure time), star centroids from images into a session of unidentified stars
(``centroid``: SEP source extraction, hot / saturated / blended rejection, PSF-fit centroids and their Cramer-Rao
bound), and lost-in-space star identification (``identify``, with the pattern engine behind ``solver_adapter``).
The renderer that draws test images with known truth lives with the simulator (``hostlink.sky.render``).
"""
