"""Batch ground calibration (docs/architecture.md): host side, float64, on the one camera model.

Modules:
- ``data``: the observations a calibration works on (centroids, reference directions, frame boundaries), built
  from a session with the reference directions of ``hostlink.sky.references``.
- ``frames``: per-frame helpers (least-squares attitude fit, padding), vectorised over frames.
- ``bundle``: the default method, a bundle adjustment over the camera and per-frame attitudes (Schur complement),
  one pass over chunks of frames per iteration (memory O(K^2 + one chunk)).
- ``distributed``: those passes, and per-sensor runs of a fleet, on a Dask cluster.
- ``interstar_methods``: seed 000 cosine / sine interstar least squares and its improved two-step iteration.
- ``seed004``: seed 004's three-step Levenberg-Marquardt.
- ``robust``: screening of misidentified stars (interstar voting), Huber weights and gating.
- ``crb``: the Cramer-Rao bound (Fisher information, attitude as nuisance) and the validation residual.
- ``report`` / ``plots``: statistics, degeneracies, the terminal table and the figures.
- ``synthetic``: random star fields through a known camera, for tests and benchmarks (not the sky simulator).
"""
