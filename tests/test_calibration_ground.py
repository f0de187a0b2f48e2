"""Ground sessions: refraction is added to the reference directions before the fit, so far from the zenith the
calibration is unbiased (and, as a control, biased without the correction)."""

import numpy as np

from hostlink.calibration.bundle import BundleOptions, bundle_adjust
from hostlink.calibration.crb import validation_residual_px
from hostlink.calibration.references import calibration_data_from_session
from hostlink.params_io import load_params
from hostlink.sky.simulate import SimConfig, data_file, seed004_camera, simulate
from onboard.site import Site, Weather

SITE = Site(40.0, 116.4, 50.0)
WEATHER = Weather(10.0, 1013.25, 0.5)


def test_ground_session_to_75_deg_zenith_distance_is_unbiased():
    truth = seed004_camera()
    cfg = SimConfig(camera=truth, frames=300, seed=21, site=SITE, weather=WEATHER, zenith_range_deg=(0.0, 75.0))
    sim = simulate(cfg)
    nominal = load_params(data_file("seed004_nominal.json"))
    data, info = calibration_data_from_session(sim.session, SITE, WEATHER)
    assert info.refraction != "none"
    res = bundle_adjust(data, nominal, BundleOptions())
    f_px_err = res.theta[0] - truth.focal_length_px
    # unbiased: the focal length within 4 of its own 1-sigma (a bias of the uncorrected size is > 20 sigma)
    assert abs(f_px_err) < 4 * np.sqrt(res.covariance[0, 0])
    v_corrected = validation_residual_px(res.theta, truth)
    raw, _ = calibration_data_from_session(sim.session)
    v_raw = validation_residual_px(bundle_adjust(raw, nominal, BundleOptions()).theta, truth)
    # control: without the correction the mapping is visibly wrong (refraction at 75 deg is ~3.6', 0.3 px over
    # the field's differential): at least 3x the corrected error
    assert v_raw > 3 * v_corrected
    assert v_corrected < 0.01
