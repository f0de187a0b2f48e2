"""Time stamps outside the years ERFA serves (hostlink.files.times.YEARS: UTC from 1960, ERFA's Earth ephemeris to
2100) are refused naming the text, on both parsing paths (one at a time, and pyarrow's vectorised pass from
VECTOR_PARSE_FROM stamps on); the span's own ends are read."""

import warnings

import erfa
import pytest

from hostlink.files.times import VECTOR_PARSE_FROM, YEARS, iso_to_utc, parse_iso_utc, parse_iso_utc_many


@pytest.mark.parametrize("text", ["1959-12-31T23:59:59Z", "2101-01-01T00:00:00Z", "9999-06-01T12:00:00.5Z"])
@pytest.mark.parametrize("n", [1, VECTOR_PARSE_FROM + 1])
def test_a_year_outside_the_span_is_refused_naming_the_text(text, n):
    texts = ["2026-03-14T02:10:00Z"] * (n - 1) + [text]
    with pytest.raises(ValueError, match=f"{text[:4]} is outside {YEARS[0]}..{YEARS[1]}") as refused:
        parse_iso_utc_many(texts)
    assert repr(text) in str(refused.value)


def test_a_fits_time_in_another_scale_is_refused_the_same_way():
    with pytest.raises(ValueError, match="year 9999 is outside"):
        iso_to_utc("9999-01-01T00:00:00", "TAI")


def test_the_span_s_first_instant_is_read_without_an_erfa_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error", erfa.ErfaWarning)
        jd1, jd2 = parse_iso_utc_many(["1960-01-01T00:00:00Z"])
    assert jd1[0] + jd2[0] == pytest.approx(2436934.5, abs=1e-9)  # 1960-01-01T00:00 UTC (ERFA's cal2jd; exact)
    assert parse_iso_utc("2100-12-31T23:59:59.999Z")[0] == YEARS[1]
