"""docs/api.md cannot rot: its worked session is run here, block by block in one namespace as in a notebook, and
each block's printed output is compared with the output the page shows under it; and the page cannot fall behind the
API: every name ``hostlink.api`` exports must appear in its code.

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


#: Inline code of the page (may wrap a line).
_INLINE_CODE = re.compile(r"`([^`]+)`")


def code_text(text: str) -> str:
    """The page's code: its fenced blocks and its inline code spans, one per line."""
    fenced = [m.group(2) for m in _FENCE.finditer(text)]
    inline = _INLINE_CODE.findall(_FENCE.sub("", text))
    return "\n".join(fenced + inline)


def documented(name: str, code: str) -> bool:
    """``name`` is in the page's code as a name of ``hostlink.api``: ``api.NAME``, or ``NAME`` on its own (not the
    attribute of another module, as in ``hostlink.calibration.chunked.NAME``, nor part of a longer name)."""
    return re.search(rf"(?:\bapi\.|(?<![\w.])){re.escape(name)}(?!\w)", code) is not None


def test_every_name_hostlink_api_exports_is_on_the_page():
    import hostlink.api as api

    exported = set(api.__all__) | set(api._lazy_table())  # __all__, and every name the module resolves lazily
    code = code_text(DOC.read_text(encoding="utf-8"))
    missing = sorted(name for name in exported if not documented(name, code))
    assert missing == [], f"docs/api.md does not document these names of hostlink.api: {', '.join(missing)}"


def test_a_name_counts_only_in_code_and_as_a_name_of_the_api():
    code = code_text("prose read_truth\n`hostlink.files.truth.read_truth(path)`, `api.read_truthy`\n")
    assert not documented("read_truth", code)  # prose, another module's attribute, a longer name
    assert documented("read_truth", code_text("`api.read_truth(path)`"))
    assert documented("Session", code_text("```python\nparts: list[Session] = []\n```\n"))
    assert documented("json_text", code_text("`api.json_text(data, *,\n  indent=2)`"))  # a span wrapped over lines


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
