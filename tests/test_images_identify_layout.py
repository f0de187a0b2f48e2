"""Identification stays readable (issue 30): hostlink.images.identify and the stage modules beside it are each under
500 lines with no function over 80, the identify module's docstring names exactly its stage modules, and the names
other code imports from hostlink.images.identify stay importable from there."""

import re
from pathlib import Path

from layout_limits import too_long

import hostlink.images.identify as identify

PACKAGE = Path(identify.__file__).parent
STAGES = ("skyindex", "matcher", "verify", "extend", "confirm", "blends", "guided")
MODULES = ("identify", "solver_adapter", *STAGES)
#: What tests, the API and other modules import from hostlink.images.identify.
IMPORTED = (
    "AMBIGUITY_MAG_MARGIN ANCHOR_STARS DEEP_ANCHOR_STARS DEEP_MATCH_STARS ENGINE_MISS_SCANNED_FRAMES FrameIdentity "
    "Identification MATCH_STARS MAX_ANCHOR_PAIRS MAX_ROUNDS PairCache SCAN_SCALES _anchor_schedule _boresight_and_roll "
    "_pairs_of_angle _pyramid_may_hit _sky _ties_by_stars _with_identities anchor_candidates catalogue_radec_deg "
    "check_field identify_frame identify_iteratively identify_session pair_catalogue"
).split()


def test_no_file_over_500_lines_and_no_function_over_80():
    assert too_long([PACKAGE / f"{name}.py" for name in MODULES], PACKAGE) == ([], [])


def test_the_docstring_names_the_stage_modules():
    named = set(re.findall(r"``(\w+)``", identify.__doc__.split("The stages,")[1]))
    assert named == set(STAGES)


def test_the_names_imported_from_identify_are_there():
    assert [name for name in IMPORTED if not hasattr(identify, name)] == []
