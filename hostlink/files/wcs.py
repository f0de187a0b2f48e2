"""FITS WCS headers of a session's attitudes (``hostlink attitude --wcs DIR``, issue 31): one header file per solved
frame, ``DIR/frame_<frame>.fits``, a primary HDU without data whose WCS is TAN at the boresight with SIP distortion
of the calibrated camera (:mod:`hostlink.sky.pointing`). astropy reads it: ``WCS(fits.getheader(path))``, and
``all_pix2world(x_px, y_px, 0)`` on a frame's centroids (the project's pixel convention is astropy's origin 0) gives
the stars' directions in the attitude's reference frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import atomic_open
from hostlink.files.times import parse_iso_utc_many
from hostlink.sky.pointing import SipModel, tan_sip_cards
from onboard.params import CameraParams

#: The Julian date of MJD 0 (MJD = JD - 2400000.5).
MJD_ZERO_JD = 2400000.5


def frame_wcs_path(directory: str | Path, frame: int) -> Path:
    """Where the header of frame counter ``frame`` goes: ``DIR/frame_<frame>.fits``."""
    return Path(directory) / f"frame_{int(frame)}.fits"


def wcs_directory(directory: str | Path) -> Path:
    """The directory of the WCS headers, created if needed; a one-line UserError when it cannot be (a file is there,
    no permission). ``hostlink attitude`` calls it before solving, so a bad ``--wcs`` writes nothing."""
    out = Path(directory)
    if out.exists() and not out.is_dir():
        raise UserError(f"--wcs {directory}: a file is there, not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--wcs {directory}: cannot create the directory ({exc.strerror})") from None
    return out


def write_wcs_headers(
    directory: str | Path, attitudes, params: CameraParams, sip: SipModel, time_known: bool, site: bool
) -> int:
    """One FITS header file per solved frame of ``attitudes`` (:class:`hostlink.sky.attitude.SessionAttitudes`)
    through the camera ``params`` with its SIP form ``sip`` (:func:`hostlink.sky.pointing.sip_model`); returns how
    many were written (unsolved frames get none). ``time_known``: the reference frame is the geocentric apparent
    place of date (RADESYS GAPPT, with DATE-OBS), else the J2000 catalogue directions (RADESYS ICRS); ``site``:
    the references were topocentric (a COMMENT says so). Each file is written atomically."""
    from astropy.io import fits

    out = wcs_directory(directory)
    theta = params.model_vector()
    # the cards every frame shares (SIP, detector, notes) are formatted once; a frame sets its own on a copy
    template = fits.PrimaryHDU().header
    for key, value, comment in tan_sip_cards(np.eye(3), theta, sip):
        template[key] = (value, comment)
    template["RADESYS"] = ("GAPPT" if time_known else "ICRS", "frame of the attitude's reference directions")
    template["IMAGEW"] = (int(params.image_size_px[0]), "[px] detector width")
    template["IMAGEH"] = (int(params.image_size_px[1]), "[px] detector height")
    template["SIPFERR"] = (sip.forward_error_px, "[px] max error of A, B (pix2world)")
    template["SIPIERR"] = (sip.inverse_error_px, "[px] max error of AP, BP (world2pix)")
    template["COMMENT"] = "hostlink attitude --wcs: TAN at the boresight, SIP = the calibrated camera's distortion"
    template["COMMENT"] = "pixel coordinates: FITS (first pixel centre = 1); astropy origin 0 = the session's x_px"
    if site:
        template["COMMENT"] = "references topocentric as observed at the site (diurnal aberration, refraction)"
    per_frame = ("CRVAL1", "CRVAL2", "CD1_1", "CD1_2", "CD2_1", "CD2_2")
    written = 0
    for k in range(attitudes.n_frames):
        c = attitudes.C[k]
        if not np.all(np.isfinite(c)):
            continue
        header = template.copy()
        for key, value, _comment in tan_sip_cards(c, theta, sip):
            if key in per_frame:
                header[key] = value
        t_utc = str(attitudes.t_utc[k] or "")
        if time_known and t_utc:
            jd1, jd2 = parse_iso_utc_many([t_utc])
            header["DATE-OBS"] = (t_utc.removesuffix("Z"), "UTC of the frame")
            header["MJD-OBS"] = (float(jd1[0] - MJD_ZERO_JD) + float(jd2[0]), "[d] UTC of the frame")
        header["FRAME"] = (int(attitudes.frame[k]), "the session's frame counter")
        header["ATTRMS"] = (float(attitudes.residual_rms_arcsec[k]), "[arcsec] attitude fit residual RMS")
        with atomic_open(frame_wcs_path(out, attitudes.frame[k]), binary=True) as fh:
            fh.write(header.tostring().encode("ascii"))
        written += 1
    return written
