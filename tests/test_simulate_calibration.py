"""An independent calibration of a simulated session recovers the camera the simulator was given (issue 2 acceptance).

Written here from docs/camera-model.md alone, sharing no code with the project's camera model or calibration: a bundle
adjustment (scipy least_squares) of (F, x0, y0, k1, k2) and one small rotation per frame, starting from the nominal
camera a user would know (seed004_nominal.json) and attitudes by an SVD solution of Wahba's problem. Residuals are the
measured centroids' ideal offsets minus the pinhole projection of C r, in pixels, so with Gaussian centroid noise
sigma they are independent with variance sigma^2 (times |d ideal / d measured|^2 = 1 +- 1e-3 for this distortion),
and the estimate's covariance is sigma^2 (J^T J)^-1 (Cramer-Rao bound of the linearised problem).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import least_squares

from hostlink.files.params import data_file
from hostlink.sky.simulate import seed004_config, simulate

N_CAM = 5  # F_px, x0, y0, k1, k2


def spec_ideal_offsets(x, y, cam):
    """docs/camera-model.md: u = x - x0, v = y - y0, radial correction (k1 r^2 + k2 r^4), ideal = measured - corr."""
    _, x0, y0, k1, k2 = cam
    u, v = x - x0, y - y0
    r2 = u * u + v * v
    radial = k1 * r2 + k2 * r2 * r2
    return u - u * radial, v - v * radial


def rodrigues(w):
    """Rotation matrices exp([w]x) for rotation vectors w (n, 3)."""
    angle = np.linalg.norm(w, axis=1)
    safe = np.where(angle > 0, angle, 1.0)
    k = w / safe[:, None]
    kx = np.zeros((w.shape[0], 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * kx + (1 - c) * (kx @ kx)


def wahba(b, r):
    """C minimising sum |b - C r|^2 (SVD solution)."""
    u, _, vt = np.linalg.svd(b.T @ r)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def radec_unit(ra_deg, dec_deg):
    ra, dec = np.radians(ra_deg), np.radians(dec_deg)
    return np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=1)


@pytest.fixture(scope="module")
def fitted():
    noise = 0.05
    cfg = replace(seed004_config(frames=120, seed=21), noise_px=noise)
    result = simulate(cfg)
    s = result.session
    nominal = json.loads(data_file("seed004_nominal.json").read_text())
    pitch = nominal["pixel_pitch_um"]
    cam0 = np.array([1000 * nominal["focal_length_mm"] / pitch, *nominal["principal_point_px"], 0.0, 0.0])
    r = radec_unit(s.ra_deg, s.dec_deg)
    _, frame = np.unique(s.frame, return_inverse=True)
    n_frames = frame.max() + 1

    def dirs(cam, x, y):
        u, v = spec_ideal_offsets(x, y, cam)
        w = np.stack([u, v, np.full_like(u, cam[0])], axis=1)
        return w / np.linalg.norm(w, axis=1, keepdims=True)

    b0 = dirs(cam0, s.x_px, s.y_px)
    c0 = np.stack([wahba(b0[frame == k], r[frame == k]) for k in range(n_frames)])

    def residuals(p):
        cam, rot = p[:N_CAM], p[N_CAM:].reshape(-1, 3)
        c = rodrigues(rot) @ c0
        br = np.einsum("nij,nj->ni", c[frame], r)
        u, v = spec_ideal_offsets(s.x_px, s.y_px, cam)
        return np.concatenate([u - cam[0] * br[:, 0] / br[:, 2], v - cam[0] * br[:, 1] / br[:, 2]])

    n = len(s)
    p0 = np.concatenate([cam0, np.zeros(3 * n_frames)])
    scale = np.concatenate([[1.0, 1.0, 1.0, 1e-10, 1e-16], np.full(3 * n_frames, 1e-4)])
    fit = least_squares(residuals, p0, method="lm", x_scale=scale, xtol=1e-12, ftol=1e-12, gtol=1e-12)
    jac = fit.jac
    cov = noise**2 * np.linalg.inv(jac.T @ jac)
    cam = cfg.camera
    truth = np.array([cam.focal_length_px, *cam.principal_point_px, cam.distortion.k1, cam.distortion.k2])
    return fit, cov[:N_CAM, :N_CAM], truth, noise, n


def test_independent_bundle_adjustment_recovers_the_simulated_camera_within_3_sigma(fitted):
    fit, cov, truth, _, _ = fitted
    sigma = np.sqrt(np.diag(cov))
    z = (fit.x[:N_CAM] - truth) / sigma
    # each parameter within 3 sigma of its Cramer-Rao uncertainty (two-sided 99.7 %)
    assert np.all(np.abs(z) < 3.0), f"normalised errors {z}"
    # and jointly: Mahalanobis distance below the chi-square(5) 99.9 % point (20.5)
    err = fit.x[:N_CAM] - truth
    assert err @ np.linalg.solve(cov, err) < 20.5
    # the fit is informative: F to better than 1 px (0.012 mm) and the principal point to a few px
    assert sigma[0] < 1.0 and sigma[1] < 5.0 and sigma[2] < 5.0


def test_fit_residuals_have_the_simulated_centroid_noise(fitted):
    fit, _, _, noise, n = fitted
    dof = 2 * n - len(fit.x)
    rms = np.sqrt(np.sum(fit.fun**2) / dof)
    # sample variance of ~3000 independent Gaussians: relative sd sqrt(2 / dof) ~ 2.6 %; 4 sd = 10 %
    assert abs(rms / noise - 1.0) < 4 * np.sqrt(2.0 / dof)
