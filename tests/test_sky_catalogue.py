"""Hipparcos 2 catalogue parsing and cache (hostlink.sky.catalogue)."""

from __future__ import annotations

import numpy as np
import pytest

from hostlink.errors import UserError
from hostlink.sky import catalogue
from hostlink.sky.apparent import hip_lookup
from hostlink.sky.catalogue import load_catalogue, parse_hip2


@pytest.fixture()
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache" / "startracker-companion"


def test_columns_match_published_hip2_values_for_sirius_vega_and_barnard():
    # van Leeuwen (2007), ESA I/311: values as printed in hip2.dat (exact to the printed digits)
    cat = load_catalogue()
    rows = hip_lookup(cat, [32349, 91262, 87937])
    np.testing.assert_array_equal(cat.hip[rows], [32349, 91262, 87937])
    np.testing.assert_allclose(cat.ra_rad[rows], [1.7678185359, 4.8735545728, 4.7028598776], rtol=0, atol=1e-12)
    np.testing.assert_allclose(cat.dec_rad[rows], [-0.2916993748, 0.6768909262, 0.0814769927], rtol=0, atol=1e-12)
    np.testing.assert_allclose(cat.plx_mas[rows], [379.21, 130.23, 548.31], rtol=0, atol=1e-9)
    np.testing.assert_allclose(cat.pmra_masyr[rows], [-546.01, 200.94, -798.58], rtol=0, atol=1e-9)
    np.testing.assert_allclose(cat.pmdec_masyr[rows], [-1223.07, 286.23, 10328.12], rtol=0, atol=1e-9)
    np.testing.assert_allclose(cat.mag[rows], [-1.0876, 0.0868, 9.4901], rtol=0, atol=1e-9)


def test_full_catalogue_has_all_117955_stars_sorted_by_hip():
    cat = load_catalogue()
    assert len(cat) == 117955  # ESA I/311 ReadMe: 117955 records
    assert cat.hip.dtype == np.int64
    assert np.all(np.diff(cat.hip) > 0)


def test_magnitude_limit_keeps_only_stars_at_or_brighter_than_the_limit():
    full = load_catalogue()
    bright = load_catalogue(6.0)
    assert np.all(bright.mag <= 6.0)
    assert len(bright) == int(np.sum(full.mag <= 6.0))


def test_cache_round_trips_the_parsed_table_exactly(private_cache):
    parsed = parse_hip2(catalogue.catalogue_file())
    first = load_catalogue()  # parses and writes the cache
    files = list(private_cache.glob("hip2-*.npz"))
    assert len(files) == 1
    second = load_catalogue()  # from the cache
    for name in ("hip", "ra_rad", "dec_rad", "pmra_masyr", "pmdec_masyr", "plx_mas", "mag"):
        np.testing.assert_array_equal(getattr(second, name), getattr(parsed, name))
        np.testing.assert_array_equal(getattr(first, name), getattr(parsed, name))


def test_unknown_hip_number_is_a_one_line_user_error():
    cat = load_catalogue(6.0)
    with pytest.raises(UserError, match="star_id 999999999"):
        hip_lookup(cat, [32349, 999999999])
