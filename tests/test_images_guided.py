"""Issue 30, guided admission of faint candidates (hostlink.images.guided): rendered frames of the real sky
(Hipparcos through a known camera and attitude), centroided with candidates, the detected stars named from the
render's truth (as identification names them), then the candidates admitted only where a catalogue star is
predicted. A frame whose faint stars are not rendered (noise alone at every predicted place) admits about what the
computed chance says; a frame with its faint stars at 3.5-5 sigma admits them with the right names."""

import math

import numpy as np
import pytest
from sky_frames import CAMERA, attitude_toward

from hostlink.files.session import Session
from hostlink.images.centroid import CentroidOptions, centroid_pixels
from hostlink.images.guided import admit, candidate_rows
from hostlink.sky.apparent import stars_at_j2000
from hostlink.sky.catalogue import load_catalogue
from hostlink.sky.render import RenderConfig, render_stars
from onboard.camera import radec_to_unit, unit_to_pixels

#: PSF sigma 1 px, 40 e- of sky, 8 e- read noise, gain 2: 10.2 e- of noise per pixel; a star's PSF-fit flux then
#: has a noise of 10.2 e- / sqrt(sum P^2) = 36 e-, so a star of Hp 7.7 (the zero point below: 146 e-) is at 4 sigma
CONFIG = RenderConfig(psf_sigma_px=1.0, zero_point_e=146.0 * 10 ** (0.4 * 7.7), hot_pixels=0, seed=3)
NOISE_E = math.sqrt(CONFIG.background_e + CONFIG.read_noise_e**2)
FLUX_SIGMA_E = NOISE_E * math.sqrt(4.0 * math.pi * CONFIG.psf_sigma_px**2)
#: The stars the detected ones are named from: as bright as identification names them.
ANCHOR_MAG = 6.5
#: A detection or candidate is the image of a rendered star within this distance [px] (the centroid noise of a 3.5
#: sigma star is ~0.4 px per axis; neighbours are tens of px apart).
MATCH_PX = 1.5


def _frame(ra_deg: float, dec_deg: float, faint_rendered: bool, seed: int):
    """(session of one frame: detected stars named from the truth, candidates unnamed; truth HIP of each row (0:
    none); the rendered stars' HIP numbers, true snr and whether SEP detected them; the catalogue)."""
    cat = load_catalogue()
    stars = stars_at_j2000(cat)
    b = radec_to_unit(stars.ra_rad, stars.dec_rad) @ attitude_toward(ra_deg, dec_deg).T
    front = np.flatnonzero(b[:, 2] > math.cos(math.radians(15.0)))
    xp, yp = unit_to_pixels(b[front], CAMERA.model_vector(np.float64))
    width, height = CAMERA.image_size_px
    on = (xp > 5) & (xp < width - 6) & (yp > 5) & (yp < height - 6)
    rows, xp, yp = front[on], xp[on], yp[on]
    if not faint_rendered:
        keep = cat.mag[rows] <= ANCHOR_MAG
        rows, xp, yp = rows[keep], xp[keep], yp[keep]
    flux_e = CONFIG.zero_point_e * 10 ** (-0.4 * cat.mag[rows])
    rendered = render_stars(xp, yp, flux_e, CAMERA.image_size_px, CONFIG, seed=seed, star_id=cat.hip[rows])
    det = centroid_pixels(rendered.image_adu, CentroidOptions(), saturation_adu=CONFIG.saturation_adu)
    c = det.candidates
    x = np.concatenate([det.x_px, c.x_px])
    y = np.concatenate([det.y_px, c.y_px])
    d = np.hypot(x[:, None] - xp[None], y[:, None] - yp[None])
    nearest = np.argmin(d, axis=1)
    truth = np.where(d[np.arange(x.size), nearest] < MATCH_PX, cat.hip[rows][nearest], 0)
    n_det = det.x_px.size
    star_id = np.zeros(x.size, dtype=np.int64)
    star_id[:n_det] = truth[:n_det]  # the detected stars, named as identification names them
    session = Session(
        frame=np.zeros(x.size, dtype=np.int64),
        t_utc=np.full(x.size, "", dtype=object),
        star_id=star_id,
        x_px=x,
        y_px=y,
        mag=np.concatenate([det.mag, c.mag]),
        extra={
            "sigma_px": np.array([f"{v:.4g}" for v in np.concatenate([det.sigma_px, c.sigma_px])], dtype=object),
            "saturated": np.array([str(int(v)) for v in det.saturated] + ["0"] * c.x_px.size, dtype=object),
            "snr": np.array([""] * n_det + [f"{v:.2f}" for v in c.snr], dtype=object),
        },
    )
    detected = np.isin(cat.hip[rows], truth[:n_det])
    true_snr = flux_e / CONFIG.gain_e_per_adu / (FLUX_SIGMA_E / CONFIG.gain_e_per_adu)
    return session, truth, cat.hip[rows], true_snr, detected, cat


@pytest.mark.parametrize("field", [(84.0, 5.0), (280.0, 40.0)], ids=["orion", "cygnus"])
def test_noise_alone_at_the_predicted_places_admits_what_chance_says(field):
    """Only the stars down to Hp 6.5 are rendered: every candidate is noise, and every catalogue star fainter than
    that is searched for at its predicted place. Named where no star is: at most the computed expectation + 3 x its
    Poisson deviation + 1 (measured: 0 and 0: the frames admitted 0 and 3, chance explains more than 5 % of that, so
    neither stands; 0.7 and 0.9 expected, of ~580 stars searched)."""
    session, truth, _, _, _, cat = _frame(*field, faint_rendered=False, seed=11)
    held = candidate_rows(session)
    assert np.count_nonzero(held) >= 50  # the noise peaks are there to be admitted
    assert np.count_nonzero(session.star_id) >= 15  # the anchors
    star_id, (record,) = admit(session, session.star_id, held, CAMERA, cat)
    assert record.searched >= 200 and record.admitted == np.count_nonzero(star_id != session.star_id)
    assert record.expected_false < 2.0
    changed = star_id != session.star_id
    wrong = np.count_nonzero(changed & (star_id != truth))
    assert wrong <= record.expected_false + 3.0 * math.sqrt(record.expected_false) + 1.0


@pytest.mark.parametrize("field", [(84.0, 5.0), (280.0, 40.0)], ids=["orion", "cygnus"])
def test_faint_stars_at_3_5_to_5_sigma_are_admitted_with_their_names(field):
    """Every catalogue star rendered at its zero-point flux: the stars at 3.5-5 sigma that SEP does not detect are
    found among the candidates and admitted with the right name: at least 60 % of them (measured 71 %: a star
    of true snr 3.5 is measured above the candidates' 3-sigma limit 69 % of the time, at 5 sigma 98 %), and no
    candidate gets a name other than its true star's beyond the computed chance (measured 0 and 1 wrong of 101 and
    124 admitted, expected 0.7 and 1.0)."""
    session, truth, hip, true_snr, detected, cat = _frame(*field, faint_rendered=True, seed=12)
    held = candidate_rows(session)
    star_id, (record,) = admit(session, session.star_id, held, CAMERA, cat)
    faint = (true_snr >= 3.5) & (true_snr <= 5.0) & ~detected
    assert np.count_nonzero(faint) >= 15
    named = {int(h) for h in star_id[held] if h}
    right = np.isin(hip[faint], list(named) if named else [-1])
    assert np.count_nonzero(right) >= 0.6 * np.count_nonzero(faint)
    changed = star_id != session.star_id
    wrong = np.count_nonzero(changed & (star_id != truth))
    assert wrong <= record.expected_false + 3.0 * math.sqrt(record.expected_false) + 1.0
