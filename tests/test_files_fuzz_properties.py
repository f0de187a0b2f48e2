"""Property-based tests (hypothesis) of the file readers: parameter JSON (``hostlink.files.params``) and session CSV
(``hostlink.files.session.read_session``). For any text a reader gives a result or a one-line UserError, never an
internal error, and what it accepts keeps the reader's promises. The oracles are those of the long run,
``python scripts/fuzz.py --decoders param_json,session_csv`` (10^6 inputs each), loaded from the script so that CI
and the long run judge alike.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scripts_loader import load_script

from hostlink.errors import UserError
from hostlink.files.params import params_from_text
from hostlink.files.session import read_session

#: Examples per property: the generators' every branch many times over, about a second each in CI.
EXAMPLES = 300
_settings = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])


fuzz = load_script("fuzz.py")

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(10**400), max_value=10**400)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.dictionaries(
            st.sampled_from(["focal_length_mm", "pixel_pitch_um", "principal_point_px", "image_size_px", "distortion"])
            | st.sampled_from(["k1", "k2", "k3", "p1", "p2", "s1", "s2", "sigma"])
            | st.text(max_size=8),
            inner,
            max_size=6,
        )
    ),
    max_leaves=20,
)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("files_fuzz") / "session.csv"


# ------------------------------------------------------------------------------------------ parameter JSON
@_settings
@given(json_values, st.booleans())
def test_any_json_value_is_a_parameter_set_or_a_one_line_refusal(value, validate):
    assert fuzz.param_text_handled(json.dumps(value, allow_nan=True), validate)


@_settings
@given(st.text(max_size=300), st.booleans())
def test_any_text_is_a_parameter_set_or_a_one_line_refusal(text, validate):
    assert fuzz.param_text_handled(text, validate)


@_settings
@given(st.integers(min_value=0, max_value=2**32 - 1), st.booleans())
def test_a_mutated_parameter_file_is_read_exactly_or_refused(seed, validate):
    assert fuzz.param_text_handled(fuzz.param_text(np.random.default_rng(seed)), validate)


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("[" * 100_000, "nested too deeply"),
        ('{"distortion":' * 100_000, "nested too deeply"),
        ('{"focal_length_mm": 7' + "0" * 5000 + "}", "more than 4300 digits"),
        ('{"focal_length_mm": 70, "pixel_pitch_um": 1' + "0" * 400 + "}", "beyond the float range"),
    ],
)
def test_parameter_texts_that_break_python_readers_are_named_refusals(text, reason):
    fields = ', "principal_point_px": [511.5, 511.5], "image_size_px": [1024, 1024]}'
    text = text[:-1] + fields if text.endswith("}") and "pixel_pitch_um" in text else text
    with pytest.raises(UserError, match=reason):
        params_from_text(text, "p.json")


def test_a_sigma_beyond_the_float_range_is_refused_naming_the_field():
    data = json.loads(fuzz._PARAM_TEXTS[0])
    text = json.dumps(data)[:-1] + ', "sigma": {"focal_length_mm": 1' + "0" * 400 + "}}"
    with pytest.raises(UserError, match="sigma.focal_length_mm"):
        fuzz.params_with_sigma_from_text(text, "p.json")


# ------------------------------------------------------------------------------------------ session CSV
@_settings
@given(st.integers(min_value=0, max_value=2**32 - 1))
def test_a_mutated_session_file_is_read_keeping_its_promises_or_refused(scratch, seed):
    assert fuzz.session_text_handled(fuzz.session_text(np.random.default_rng(seed)), scratch)


@_settings
@given(
    st.lists(
        st.tuples(
            st.sampled_from(fuzz._ODD_FIELDS + ["0", "1", "2"]),
            st.sampled_from(fuzz._ODD_FIELDS + ["0", "52419"]),
            st.sampled_from(fuzz._ODD_FIELDS + ["512.25"]),
            st.sampled_from(fuzz._ODD_FIELDS + ["100.5"]),
        ),
        max_size=6,
    )
)
def test_session_rows_of_odd_fields_are_read_keeping_the_promises_or_refused(scratch, rows):
    text = "frame,star_id,x_px,y_px\n" + "".join(",".join(r) + "\n" for r in rows)
    assert fuzz.session_text_handled(text, scratch)


@pytest.mark.parametrize("value", ["9" * 30, str(2**53 + 1), "1e300"])
@pytest.mark.parametrize("column", ["frame", "star_id"])
def test_an_integer_column_beyond_exact_float_integers_is_refused_not_rounded(value, column, scratch):
    row = {"frame": "1", "star_id": "0", "x_px": "1.5", "y_px": "2.5"}
    row[column] = value
    scratch.write_text("frame,star_id,x_px,y_px\n" + ",".join(row.values()) + "\n")
    with pytest.raises(UserError, match=f"column {column}: not an integer"):
        read_session(scratch)


def test_the_largest_exact_integer_is_read_exactly(scratch):
    scratch.write_text(f"frame,star_id,x_px,y_px\n{2**53 - 1},0,1.5,2.5\n")
    session = read_session(scratch)
    assert int(session.frame[0]) == 2**53 - 1 and math.isfinite(session.x_px[0])
