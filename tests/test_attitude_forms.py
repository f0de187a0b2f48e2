"""The attitude in the forms engineers and astronomers use (issue 31), checked against outside authorities: the
quaternion against scipy's Rotation, the roll against a star stepped north through the camera, and the FITS WCS
headers of ``attitude --wcs`` against astropy: for every frame of the README's worked session,
``WCS.all_pix2world`` on the frame's centroids gives the stars' directions within the calibration's residual."""

import csv
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hostlink.cli import main
from hostlink.files.params import load_params
from hostlink.files.session import read_session
from hostlink.sky.pointing import attitude_quaternion, boresight_radec_roll, sip_model, weng_as_sip
from hostlink.sky.references import session_references
from onboard.camera import distortion_px, offsets_from_direction, pixels_to_unit, radec_to_unit


def angle_rad(a, b):
    """Angle between unit vectors row by row, by atan2 (accurate at small angles, unlike arccos)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


@pytest.fixture(scope="module")
def worked(tmp_path_factory):
    """The README's worked session: the example's files, 1000 frames, calibrate, attitude --wcs."""
    d = tmp_path_factory.mktemp("worked")
    assert main(["example", str(d / "ex")]) == 0
    d = d / "ex"
    s, cal, att, wcs = (str(d / n) for n in ("s.csv", "cal.json", "attitude.csv", "wcs"))
    assert main(["simulate", "--camera", str(d / "true-camera.json"), "--frames", "1000", "--out", s]) == 0
    assert main(["calibrate", s, "--nominal", str(d / "nominal.json"), "--out", cal, "--quiet"]) == 0
    assert main(["attitude", s, "--params", cal, "--out", att, "--wcs", wcs]) == 0
    with open(att, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {"session": read_session(s), "params": load_params(cal), "rows": rows, "wcs": d / "wcs"}


def matrix(row):
    return np.array([float(row[f"c{i}{j}"]) for i in (1, 2, 3) for j in (1, 2, 3)]).reshape(3, 3)


def test_quaternion_is_scipys_scalar_first_rotation_from_reference_to_sensor_axes():
    """Random rotations and the four branches of Shepperd's method (rotations by ~180 deg about each axis, where q0
    is near zero): the quaternion is scipy's Rotation.from_matrix(C.T) scalar first, sign fixed to q0 >= 0."""
    rng = np.random.default_rng(7)
    mats = list(Rotation.random(500, random_state=rng).as_matrix())
    for axis in np.eye(3):
        mats.append(Rotation.from_rotvec((math.pi - 1e-9) * axis).as_matrix())
    mats.append(np.eye(3))
    for c in mats:
        q = attitude_quaternion(c)
        ref = np.roll(Rotation.from_matrix(c.T).as_quat(), 1)  # scipy's (x, y, z, w) -> (w, x, y, z); every scipy
        ref = -ref if ref[0] < 0 else ref
        assert q[0] >= 0 and np.allclose(q, ref, atol=1e-12)  # rounding of a unit quaternion from a float64 matrix


def test_the_attitude_file_carries_quaternion_boresight_and_roll(worked):
    """Every solved row: the quaternion rebuilds C (scipy), the boresight is C's third row as RA/Dec, and the roll
    is the image direction of a point 1 arcsec north of the boresight, seen through the camera (ideal offsets: the
    principal point is the boresight's image)."""
    theta = worked["params"].model_vector()
    for row in worked["rows"]:
        assert row["status"] == "ok"
        c = matrix(row)
        q = np.array([float(row[k]) for k in ("q0", "q1", "q2", "q3")])
        rebuilt = Rotation.from_quat(np.roll(q, -1)).as_matrix().T  # (w, x, y, z) -> scipy's (x, y, z, w)
        assert np.allclose(rebuilt, c, atol=1e-12)
        ra, dec, roll = (float(row[k]) for k in ("boresight_ra_deg", "boresight_dec_deg", "roll_deg"))
        bore = radec_to_unit(np.radians([ra]), np.radians([dec]))[0]
        assert angle_rad(bore, c[2]) < 1e-12
        # the meridian through the boresight is a great circle, which the pinhole (gnomonic) projection maps to a
        # straight line through the principal point: a point 1" north lies exactly along the projected north
        assert abs(dec) < 89.9
        north = radec_to_unit(np.radians([ra]), np.radians([dec]) + math.radians(1 / 3600))
        u, v = offsets_from_direction(north @ c.T, theta[0])
        expected = math.degrees(math.atan2(u[0], -v[0]))
        assert abs((roll - expected + 180) % 360 - 180) < 1e-6  # deg: float64 rounding of 0.03 px offsets


def test_the_sip_form_is_the_weng_model_exactly():
    """Weng's distortion is a polynomial of degree 7: its SIP form equals onboard.camera.distortion_px at random
    points to rounding, with every term present (all ten parameters nonzero)."""
    theta = np.array([5852.0, 500.0, 530.0, -2e-10, 3.5e-15, -4e-21, 2e-7, -1.5e-7, 1e-7, -2e-7])
    order, a, b = weng_as_sip(theta)
    assert order == 7
    rng = np.random.default_rng(3)
    u, v = rng.uniform(-700, 700, (2, 200))
    dx, dy = distortion_px(u, v, theta)
    sip_dx = -sum(c * u**p * v**q for (p, q), c in a.items())
    sip_dy = -sum(c * u**p * v**q for (p, q), c in b.items())
    assert np.max(np.abs(sip_dx - dx)) < 1e-12 and np.max(np.abs(sip_dy - dy)) < 1e-12  # px; |d| up to ~5 px
    sip = sip_model(theta, (1024, 1024))
    # forward: exact polynomials, rounding only; inverse: a fitted order-7 polynomial of a ~5 px distortion, held to
    # 1e-3 px, 50 x below the 0.05 px centroid noise the calibrations here work at (the worked camera fits to 3.8e-5)
    assert sip.forward_error_px < 1e-12 and sip.inverse_error_px < 1e-3


def test_astropy_reads_every_frames_wcs_as_the_calibrated_camera(worked):
    """For every frame of the worked session, astropy's WCS(header).all_pix2world on the frame's centroids (origin
    0: the session's pixel convention) gives (a) the direction the calibrated camera and the frame's attitude give,
    within the header's stated SIP error plus 1e-6 px (the header's printed digits), and so (b) each star's catalogue
    direction within its own calibration residual plus that; the frame's RMS is the file's residual_rms_arcsec; and
    all_world2pix returns the centroids within the stated inverse error."""
    import warnings

    from astropy.io import fits
    from astropy.utils.exceptions import AstropyWarning
    from astropy.wcs import WCS

    session, params = worked["session"], worked["params"]
    theta = params.model_vector()
    refs = session_references(session)
    focal_px = float(theta[0])
    checked = 0
    for k, sl in enumerate(session.frame_slices()):
        row = worked["rows"][k]
        header = fits.getheader(worked["wcs"] / f"frame_{int(session.frame[sl.start])}.fits")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", AstropyWarning)  # "more axes than the image": a header without data
            wcs = WCS(header)
        rows = np.arange(sl.start, sl.stop)[refs.usable[sl]]
        x, y = session.x_px[rows], session.y_px[rows]
        ra, dec = wcs.all_pix2world(x, y, 0)
        w = radec_to_unit(np.radians(ra), np.radians(dec))
        c = matrix(row)
        model = pixels_to_unit(x, y, theta) @ c  # C^T b
        r = refs.r[rows]
        tol_rad = (header["SIPFERR"] + 1e-6) / focal_px
        assert np.all(angle_rad(w, model) <= tol_rad)
        assert np.all(angle_rad(w, r) <= angle_rad(model, r) + tol_rad)
        if int(row["n_used"]) == rows.size:
            rms_arcsec = math.degrees(math.sqrt(np.mean(angle_rad(w, r) ** 2))) * 3600
            assert abs(rms_arcsec - float(row["residual_rms_arcsec"])) < 1e-4  # the file's 4 decimals
        assert header["ATTRMS"] == pytest.approx(float(row["residual_rms_arcsec"]), abs=5e-5)
        xb, yb = wcs.all_world2pix(ra, dec, 0)
        assert np.max(np.hypot(xb - x, yb - y)) <= header["SIPIERR"] + 1e-6
        checked += 1
    assert checked == session.n_frames == 1000


def test_boresight_and_roll_is_the_one_identify_prints():
    """One formula in one place: identify's boresight/roll is hostlink.sky.pointing's."""
    from hostlink.images import identify

    c = Rotation.random(random_state=np.random.default_rng(2)).as_matrix()
    assert identify._boresight_and_roll(c) == boresight_radec_roll(c)
