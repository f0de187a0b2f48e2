"""The files room stays readable: the session package's docstring names the modules that exist, and no module of
``hostlink.files`` (the session package's included) is over 500 lines or has a function over 80; every name the
session module had before its split is still importable from ``hostlink.files.session``."""

import pkgutil
import re
from pathlib import Path

from layout_limits import too_long

import hostlink.files as files
import hostlink.files.session as session

ROOM = Path(files.__file__).parent

#: The public names of ``hostlink.files.session`` when it was one module (820 lines), which callers import.
NAMES_BEFORE_THE_SPLIT = (
    "CSV_BLOCK_BYTES DEFAULT_CHUNK_FRAMES DETECTOR_MARGIN_PX MAY_BE_ABSENT OPTIONAL_COLUMNS PIXEL_SIGMA_FORMAT "
    "REQUIRED_COLUMNS Session SessionSource SessionWriter cell_numbers check_on_detector concatenate_sessions "
    "pixel_sigma_text read_session read_session_chunks session_filled session_flag session_number session_paths "
    "write_session"
).split()


def test_session_package_docstring_names_exactly_its_modules():
    modules = {m.name for m in pkgutil.iter_modules(session.__path__)}
    named = set(re.findall(r":mod:`~hostlink\.files\.session\.(\w+)`", session.__doc__))
    assert named == modules


def test_no_file_over_500_lines_and_no_function_over_80():
    assert too_long(list(ROOM.rglob("*.py")), ROOM) == ([], [])


#: Public names added since the split (the images' size: issue 30).
NAMES_ADDED = "IMAGE_SIZE_COLUMNS image_size_mismatch image_sizes_px".split()


def test_every_name_of_the_session_module_is_still_there():
    missing = [name for name in NAMES_BEFORE_THE_SPLIT + NAMES_ADDED if not hasattr(session, name)]
    assert missing == [] and sorted(session.__all__) == sorted(NAMES_BEFORE_THE_SPLIT + NAMES_ADDED)
