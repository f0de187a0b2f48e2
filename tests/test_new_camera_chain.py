"""Issue 30, a camera the project has never seen, through the commands a user runs (``hostlink centroid`` ->
``identify`` -> ``calibrate``, each its own process): a 35 mm lens on 6.9 um pixels (F = 5072 px), 1280 x 960 px
(14.4 x 10.8 deg), a little barrel distortion and the principal point 12 px off centre, stars rendered by
hostlink.sky.render to Hp 8.5 with a sharp undersampled PSF (sigma 0.77 px), 60 hot pixels per frame, a 12-bit ADC,
written as FITS with DATE-OBS; the nominal 8 % short, or 8 % long with its principal point 30 px off in x and y.

Measured (scripts/newcamera.py's cases on this render, docs/realsky.md "A new camera: what was tried"): 6 of 6 frames,
1150 of the 1151 true stars centroided named right, none wrong, 58 of the 60 hot pixels per frame rejected; f within
1 sigma of the truth, residual 0.053 px."""

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from astropy.io import fits

from hostlink.files.session import read_session
from hostlink.sky.render import RenderConfig, render_frame
from hostlink.sky.simulate import SimConfig, simulate
from onboard.params import CameraParams, Distortion, params_to_dict

TRUE = CameraParams(
    focal_length_mm=35.0,
    pixel_pitch_um=6.9,
    principal_point_px=(652.0, 471.0),
    image_size_px=(1280, 960),
    distortion=Distortion(k1=-3e-9),
)
FRAMES = 6
CONFIG = RenderConfig(psf_sigma_px=0.77, bits=12, hot_pixels=60, hot_pixel_e=3000.0, seed=4)
#: a centroid is the image of a true star within this distance [px] (centroid errors here are < 0.3 px; stars at
#: Hp 8.5 on this field lie tens of px apart)
MATCH_PX = 1.5


def hostlink(*args: str) -> subprocess.CompletedProcess:
    code = "import sys; from hostlink.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, check=False)


@pytest.fixture(scope="module")
def centroided(tmp_path_factory):
    """The rendered frames as FITS files, centroided by the command; the renders (the truth)."""
    work = tmp_path_factory.mktemp("newcamera")
    sim = simulate(
        SimConfig(camera=TRUE, frames=FRAMES, noise_px=0.0, min_stars=10, max_stars=2000, maglim=8.5, seed=30)
    )
    renders, paths = [], []
    for k in range(FRAMES):
        rendered = render_frame(sim, k, CONFIG)
        hdu = fits.PrimaryHDU(rendered.image_adu)
        hdu.header["DATE-OBS"] = sim.session.t_utc[sim.session.frame_starts[k]].replace("Z", "")
        paths.append(work / f"frame{k}.fits")
        hdu.writeto(paths[-1])
        renders.append(rendered)
    done = hostlink("centroid", *map(str, paths), "--quiet", "--out", str(work / "c.csv"))
    assert done.returncode == 0, done.stderr
    return work, renders


@pytest.mark.parametrize(("focal_factor", "offset_px"), [(0.92, 0.0), (1.08, 30.0)], ids=["f-8%", "f+8%,pp+30px"])
def test_an_undersampled_camera_is_identified_and_calibrated_from_a_wrong_nominal(centroided, focal_factor, offset_px):
    work, renders = centroided
    x0, y0 = 639.5 + offset_px, 479.5 + offset_px
    nominal = replace(TRUE, focal_length_mm=35.0 * focal_factor, principal_point_px=(x0, y0), distortion=Distortion())
    nominal_path = work / f"nominal_{focal_factor}.json"
    nominal_path.write_text(json.dumps(params_to_dict(nominal)))
    ident, cal = work / f"i_{focal_factor}.csv", work / f"cal_{focal_factor}.json"
    done = hostlink("identify", str(work / "c.csv"), "--nominal", str(nominal_path), "--quiet", "--out", str(ident))
    assert done.returncode == 0, done.stderr
    done = hostlink("calibrate", str(ident), "--nominal", str(nominal_path), "--quiet", "--out", str(cal))
    assert done.returncode == 0, done.stderr

    session = read_session(ident)
    candidate = np.array([bool(str(v).strip()) for v in session.extra.get("snr", [""] * len(session))])
    detected = right = wrong = 0
    for k, rendered in enumerate(renders):
        m = session.frame == k
        d = np.hypot(
            session.x_px[m][:, None] - rendered.truth_x_px[None], session.y_px[m][:, None] - rendered.truth_y_px[None]
        )
        j = np.argmin(d, axis=1)
        near = d[np.arange(j.size), j] < MATCH_PX
        named, truth = session.star_id[m], rendered.truth_star_id[j]
        detected += np.count_nonzero(near & ~candidate[m])
        right += np.count_nonzero(near & (named == truth) & (named != 0))
        wrong += np.count_nonzero((named != 0) & ~(near & (named == truth)))
    assert detected >= 150 * FRAMES  # the centroider found the stars at all (1151 here)
    assert wrong == 0
    assert right >= 0.98 * detected

    result = json.loads(cal.read_text())
    # the focal length within 4 of its stated sigmas (0.0005 mm: 1e-5 relative) of the truth
    assert abs(result["focal_length_mm"] - TRUE.focal_length_mm) < 4 * result["sigma"]["focal_length_mm"]
    # the principal point: on this 14 deg field with decentering and prism free its 1-sigma is ~8 px, at the limit
    # above which calibrate holds it at the nominal (docs/calibration.md); estimated, it lies within 25 px of the
    # truth (3 sigma); held, the result says so with that reason (the nominal here is 42 px off: a user is told)
    held = {h["parameter"]: h for h in result["held"]}
    if {"x0", "y0"} & held.keys():
        assert all(held[p]["sigma_effect_px"] > held[p]["limit_px"] for p in ("x0", "y0") if p in held)
        assert result["principal_point_px"] == list(nominal.principal_point_px)
    else:
        assert np.hypot(*(np.array(result["principal_point_px"]) - TRUE.principal_point_px)) < 25.0
    # residual: the centroid noise of these stars (median sigma_px ~0.05 px), not a model error of a px
    assert result["residuals"]["after"]["rms_px"] < 0.1
