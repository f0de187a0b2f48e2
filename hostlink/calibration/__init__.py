"""Batch ground calibration (docs/architecture.md): host side, float64, on the one camera model (docs/camera-model.md).

Modules (the bundle adjustment's split along its algorithm: docs/calibration.md):
- ``data``: the observations a calibration works on (centroids, reference directions, frame boundaries), built
  from a session with the reference directions of ``hostlink.sky.references``; spooled chunks.
- ``frames``: per-frame helpers (least-squares attitude fit, small rotations), vectorised over frames.
- ``model``: the measurement model (projection, whitening, residuals and Jacobians).
- ``normal``: the normal equations (accumulation, Schur complement, solve, covariance).
- ``source`` / ``passes``: the frames as chunks, and one pass over them (per-pass sums, gating, regating).
- ``acceleration``: the geodesic acceleration of a large Gauss-Newton step.
- ``lm``: the Levenberg-Marquardt round, its termination tests and status.
- ``bundle``: the default method, the rounds of the bundle adjustment over the camera and per-frame attitudes.
- ``reference``: a dense textbook Gauss-Newton / Levenberg-Marquardt solver, the reference the tests hold
  ``bundle`` to.
- ``run``: one calibration run: the method chosen, the seed methods with their gating, the in-memory entry.
- ``chunked``: the bundle's one driver over chunks of frames (pre-pass, voting, fit, held parameters,
  statistics), for a session in memory (one chunk) or read from files of any length (spooled chunks).
- ``outcome``: what a run gives (the outcome, the failure rule, the result file's extras).
- ``distributed``: the passes, and per-sensor runs of a fleet, on a Dask cluster.
- ``interstar_methods``: seed 000 cosine / sine interstar least squares and its improved two-step iteration.
- ``seed004``: seed 004's three-step Levenberg-Marquardt.
- ``robust``: the pre-pass (focal scale, parity), interstar voting, Huber weights.
- ``prepass_sample``: the frames and stars the pre-pass looks at (its bounds on frames and on star pairs).
- ``noisefloor``: the stars' noise as a scale of their given sigma_px and a floor common to the session, two
  variance components estimated from the residuals (restricted maximum likelihood).
- ``noisefield``: a floor that grows with the field radius (floor^2 = b + c q), its estimate and the likelihood-ratio
  choice against the constant one.
- ``floorfit``: the fit with the floor re-estimated between fits, and its record in the result.
- ``crb``: the Cramer-Rao bound (Fisher information, attitude as nuisance) and the validation residual.
- ``mirror``: the principal point with decentering and prism free: the mirrored minimum, fitted and reported.
- ``rejected``: the identified stars a calibration did not use, with their reasons (the ``--rejected`` file).
- ``report`` / ``plots``: statistics, degeneracies, the terminal table and the figures.
- ``synthetic``: random star fields through a known camera, exact truth, for judging a method (not the sky simulator).
- ``status``: the calibration status a result file carries (converged, not converged, failed), which `hostlink upload`
  checks.
- ``holdout``: judging a calibration on stars it did not see.
- ``replay``: the host driver of the onboard recursive calibration (a session fed frame by frame).
"""
