"""Session CSV files (docs/file-formats.md): round trip, frames, unidentified rows, one-line errors for bad files."""

import numpy as np
import pytest

from hostlink.errors import UserError
from hostlink.files.session import Session, read_session, write_session

HEADER = "frame,t_utc,star_id,x_px,y_px,mag,ra_deg,dec_deg\n"


def _write(tmp_path, text, name="s.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_round_trip_keeps_values_frames_and_extra_columns(tmp_path):
    s = Session(
        frame=np.array([0, 0, 1]),
        t_utc=np.array(["2026-03-14T02:10:00.000Z"] * 2 + ["2026-03-14T02:10:01.000Z"], dtype=object),
        star_id=np.array([32349, 0, 11767]),
        x_px=np.array([1.25, 2.5, 1023.123456]),
        y_px=np.array([3.0, 4.0, 0.000001]),
        mag=np.array([-1.46, 7.0, 1.97]),
        ra_deg=np.array([101.2871553, np.nan, 37.9546]),
        dec_deg=np.array([-16.7161159, np.nan, 89.2641]),
        extra={"snr": np.array(["10", "3", "50"], dtype=object)},
    )
    path = tmp_path / "s.csv"
    write_session(path, s)
    r = read_session(path)
    assert r.n_frames == 2 and list(r.frame_starts) == [0, 2, 3]
    np.testing.assert_allclose(r.x_px, s.x_px, atol=5e-7)  # written with 6 decimals
    np.testing.assert_allclose(r.ra_deg[[0, 2]], s.ra_deg[[0, 2]], atol=5e-11)  # 10 decimals of a degree
    assert np.isnan(r.ra_deg[1]) and r.star_id[1] == 0
    assert list(r.extra["snr"]) == ["10", "3", "50"]
    jd1, jd2 = r.frame_times_jd()
    assert abs(((jd1[1] - jd1[0]) + (jd2[1] - jd2[0])) * 86400 - 1.0) < 1e-6


@pytest.mark.parametrize(
    "body, message",
    [
        ("", "empty file"),
        ("frame,t_utc,x_px,y_px\n", "missing required column(s) star_id"),
        (HEADER + "0,2026-03-14T02:10:00Z,5,abc,1,2,3,4\n", "line 2, column x_px: not a number"),
        (HEADER + "0,2026-03-14T02:10:00Z,5,1,1,2,3\n", "line 2: expected 8 fields, found 7"),
        (HEADER + "1,2026-03-14T02:10:00Z,5,1,1,2,3,4\n0,2026-03-14T02:10:00Z,5,1,1,2,3,4\n", "not in time order"),
        (HEADER + "0,yesterday,5,1,1,2,3,4\n", "not an ISO 8601 UTC time"),
        (HEADER + "0,2026-02-30T02:10:00Z,5,1,1,2,3,4\n", "invalid date"),
        (HEADER + "0,2026-03-14T02:10:00Z,5,1,1,2,,\n", "identified star without a finite ra_deg"),
        (HEADER + "0,2026-03-14T02:10:00Z,5.5,1,1,2,3,4\n", "column star_id: not an integer"),
        (HEADER + "0,2026-03-14T02:10:00Z,5,nan,1,2,3,4\n", "column x_px: not finite"),
        ("frame,t_utc,star_id,x_px,y_px,ra_deg\n", "ra_deg and dec_deg must both be present"),
    ],
)
def test_malformed_session_is_a_one_line_error_naming_the_place(tmp_path, body, message):
    with pytest.raises(UserError) as info:
        read_session(_write(tmp_path, body))
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_missing_file_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="no such file"):
        read_session(tmp_path / "nope.csv")


def test_minimal_columns_without_reference_directions_are_accepted(tmp_path):
    s = read_session(_write(tmp_path, "frame,t_utc,star_id,x_px,y_px\n3,2026-03-14T02:10:00.5Z,7,1.5,2.5\n"))
    assert s.ra_deg is None and s.mag is None and s.n_frames == 1


def test_pixel_sigma_text_is_four_significant_digits_as_numpy_scalars_give_and_empty_without_a_value():
    from hostlink.files.session import pixel_sigma_text

    rng = np.random.default_rng(7)
    values = np.concatenate([10.0 ** rng.uniform(-4, 3, 2000), [0.0, 0.30000000000000004, 12345.6, np.nan, np.inf]])
    text = pixel_sigma_text(values)
    finite = np.isfinite(values)
    assert list(text[finite]) == [f"{v:.4g}" for v in values[finite]]  # numpy float64 scalars, as blends wrote them
    assert list(text[~finite]) == ["", ""]
    assert list(pixel_sigma_text(np.array([0.123456, 1234.5]))) == ["0.1235", "1234"]  # half to even at 1234.5
    np.testing.assert_allclose(np.array(text[finite], dtype=float), values[finite], rtol=5e-4)  # 4 digits: <= 5e-4
