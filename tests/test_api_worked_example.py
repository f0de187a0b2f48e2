"""docs/api.md cannot rot: its worked session is run here, block by block in one namespace as in a notebook, and
each block's printed output is compared with the output the page shows under it.

The page is the one copy of the example code. After a deliberate change, rewrite the page's outputs with
``python tests/test_api_worked_example.py --write`` and review the diff.
"""

from __future__ import annotations

import contextlib
import io
import re
import sys
from pathlib import Path

DOC = Path(__file__).resolve().parent.parent / "docs" / "api.md"
#: A fenced block: its language and its text.
_FENCE = re.compile(r"^```(\w*)\n(.*?)^```\n", re.S | re.M)
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def example_blocks(text: str) -> list[tuple[str, str | None, int]]:
    """(python code, the ``text`` block right after it or None, line number) of every python block of the page."""
    fences = [(m.group(1), m.group(2), m.start(), m.end()) for m in _FENCE.finditer(text)]
    out = []
    for k, (lang, body, start, end) in enumerate(fences):
        if lang != "python":
            continue
        nxt = fences[k + 1] if k + 1 < len(fences) else None
        follows = nxt is not None and nxt[0] == "text" and text[end : nxt[2]].strip() == ""
        out.append((body, nxt[1] if follows else None, text.count("\n", 0, start) + 1))
    return out


def run_blocks(blocks: list[tuple[str, str | None, int]]) -> list[str]:
    """Run the blocks in one namespace (in the current directory); the stdout of each."""
    namespace: dict = {"__name__": "docs_api_example"}
    outputs = []
    for code, _, line in blocks:
        buffer = io.StringIO()
        with contextlib.redirect_stdout(buffer):
            exec(compile(code, f"{DOC.name}:{line}", "exec"), namespace)
        outputs.append(buffer.getvalue())
    return outputs


def _last_digit(number: str) -> float:
    """One unit in the last printed place of a decimal string; 0 for an integer (counts are exact)."""
    mantissa, _, exponent = number.lower().partition("e")
    if "." not in mantissa:
        return 0.0
    return 10.0 ** (int(exponent or 0) - len(mantissa.split(".")[1]))


def outputs_agree(got: str, want: str) -> bool:
    """Equal text and integers; decimals equal to one unit of their last printed digit (a value that moved by
    rounding noise, e.g. another LAPACK build at the oldest dependency versions, may round the other way; nothing
    larger passes)."""
    if _NUMBER.sub("#", got) != _NUMBER.sub("#", want):
        return False
    pairs = zip(_NUMBER.findall(got), _NUMBER.findall(want), strict=True)
    return all(abs(float(g) - float(w)) <= _last_digit(w) * (1 + 1e-9) for g, w in pairs)


def test_the_worked_session_of_docs_api_prints_what_the_page_shows(tmp_path, monkeypatch):
    blocks = example_blocks(DOC.read_text(encoding="utf-8"))
    assert len(blocks) >= 6  # import, simulate, calibrate, replay, attitude, emulator
    assert all(expected is not None for _, expected, _ in blocks[1:])  # every step shows its output
    monkeypatch.chdir(tmp_path)
    for (_, expected, line), got in zip(blocks, run_blocks(blocks), strict=True):
        if expected is not None:
            assert outputs_agree(got, expected), f"docs/api.md line {line}: printed\n{got}\nthe page shows\n{expected}"
    assert (tmp_path / "calibrated.json").is_file() and (tmp_path / "attitude.csv").is_file()


def test_the_output_comparison_allows_the_last_digit_and_nothing_more():
    assert outputs_agree("f = 70.2272 mm\n", "f = 70.2273 mm\n")
    assert not outputs_agree("f = 70.2270 mm\n", "f = 70.2272 mm\n")
    assert not outputs_agree("f = 70.2272 um\n", "f = 70.2272 mm\n")
    assert outputs_agree("generation 2\n", "generation 2\n") and not outputs_agree("generation 3\n", "generation 2\n")


def _write_outputs() -> None:
    """Rewrite the page's output blocks with what the example prints now (run from a scratch directory)."""
    import tempfile

    text = DOC.read_text(encoding="utf-8")
    blocks = example_blocks(text)
    with tempfile.TemporaryDirectory() as scratch, contextlib.chdir(scratch):
        outputs = run_blocks(blocks)
    for (code, expected, _), got in zip(blocks, outputs, strict=True):
        if expected is not None:
            text = text.replace(
                f"```python\n{code}```\n\n```text\n{expected}```\n", f"```python\n{code}```\n\n```text\n{got}```\n"
            )
    DOC.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    if sys.argv[1:] == ["--write"]:
        sys.path.insert(0, str(DOC.parent.parent))
        _write_outputs()
    else:
        sys.exit("usage: python tests/test_api_worked_example.py --write")
