"""The flight-code rules of the C firmware core (docs/port-kit.md sections 5 and 6), held on every file shipped in
onboard/c (``estimator_none.c`` included, which the library build leaves out when ``estimator_seam.c`` exists):

- C99 with the flight-code warnings as errors (``firmware_c.WARNING_FLAGS``) plus ``-Wvla`` (no variable-length
  array), with every C compiler on the machine among cc, gcc and clang;
- no dynamic memory, no I/O, no clock, no non-local jumps: only <stdint.h>, <stddef.h>, <string.h>, <math.h> and
  <float.h> from the C library, and none of malloc/calloc/realloc/free/alloca/printf/... named in the code;
- no recursion: the call graph GCC writes (``-fcallgraph-info``, every translation unit at -O0 so no call is inlined
  away) has no cycle, and the only indirect calls are banks.c's calls of the HAL (``banks_hal_t``), which leave the
  core;
- fixed-width types for stored values: no struct member is a plain int/long/short/unsigned."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from importlib import resources
from pathlib import Path

import pytest

from hostlink.portkit import firmware_c
from hostlink.portkit.export_c import generate_c

#: The C library headers the core may include: fixed-width integers, size_t, memcpy/memset, the maths functions
#: numpy's float32 results come from, and the float limits. Nothing that allocates, does I/O or reads a clock.
ALLOWED_SYSTEM_HEADERS = {"stdint.h", "stddef.h", "string.h", "math.h", "float.h"}
#: Names that mean dynamic memory, I/O, a clock, an exit or a non-local jump.
FORBIDDEN_NAMES = (
    "malloc", "calloc", "realloc", "free", "alloca", "printf", "fprintf", "sprintf", "snprintf", "puts", "putchar",
    "fopen", "fwrite", "fread", "FILE", "time", "clock", "exit", "abort", "setjmp", "longjmp", "getenv",
)  # fmt: skip
#: The only source files that may call through a function pointer: the flash HAL's callbacks (banks_hal_t).
INDIRECT_CALLERS = {"banks.c"}

COMPILERS = sorted({os.path.realpath(p) for p in (shutil.which(n) for n in ("cc", "gcc", "clang")) if p is not None})
pytestmark = pytest.mark.skipif(not COMPILERS, reason="no C compiler on this machine")


def _shipped() -> dict[str, str]:
    folder = resources.files("onboard").joinpath("c")
    return {p.name: p.read_text() for p in folder.iterdir() if p.name.endswith((".c", ".h"))}


def _code(text: str) -> str:
    """The text without comments and string literals (a name in a comment is not a call)."""
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    text = re.sub(r"//[^\n]*", " ", text)
    return re.sub(r'"(\\.|[^"\\])*"', '""', text)


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    """Every shipped onboard/c file beside the generated codec headers it includes."""
    work = tmp_path_factory.mktemp("flight")
    for name, text in {**generate_c(), **_shipped()}.items():
        (work / name).write_text(text)
    return work


def test_the_shipped_core_includes_estimator_none_and_the_seam():
    names = set(_shipped())
    assert {"estimator_none.c", "estimator_seam.h", "firmware.c", "banks.c"} <= names


@pytest.mark.parametrize("compiler", COMPILERS)
def test_every_file_compiles_as_c99_with_the_warnings_as_errors_and_no_vla(tree, compiler):
    for name in sorted(_shipped()):
        if not name.endswith(".c"):
            continue
        cmd = [compiler, *firmware_c.WARNING_FLAGS, "-Wvla", "-ffp-contract=off", "-O2", "-c", name, "-o", "x.o"]
        run = subprocess.run(cmd, cwd=tree, capture_output=True, text=True)
        assert run.returncode == 0 and run.stderr == "", f"{compiler} {name}:\n{run.stderr}"


def test_no_allocation_io_clock_or_jump_from_the_c_library():
    for name, text in sorted(_shipped().items()):
        system = set(re.findall(r"#\s*include\s*<([^>]+)>", text))
        assert system <= ALLOWED_SYSTEM_HEADERS, (name, system - ALLOWED_SYSTEM_HEADERS)
        code = _code(text)
        used = [n for n in FORBIDDEN_NAMES if re.search(rf"\b{n}\b", code)]
        assert not used, (name, used)


def test_no_struct_member_has_a_plain_integer_type():
    plain = re.compile(r"^[ \t]*(?:const\s+)?(?:signed\s+|unsigned\s+)?(?:int|long|short|unsigned)\b[^(;\n]*;", re.M)
    bodies = 0
    for name, text in sorted(_shipped().items()):
        for body in re.findall(r"struct\s*\w*\s*\{(.*?)\}", _code(text), flags=re.S):
            bodies += 1
            assert not plain.findall(body), (name, plain.findall(body))
    assert bodies > 10  # the structs were read (the core declares some twenty)


def _call_graph(tree: Path, gcc: str) -> tuple[dict[str, set[str]], set[str]]:
    """Caller -> callees over every translation unit, and the files with an indirect call (GCC's call graph)."""
    edges: dict[str, set[str]] = {}
    indirect: set[str] = set()
    for source in sorted(tree.glob("*.c")):
        if source.name not in _shipped():
            continue  # the generated codec is not the core's code
        obj = tree / "cg" / (source.stem + ".o")
        obj.parent.mkdir(exist_ok=True)
        cmd = [gcc, "-std=c99", "-O0", "-fcallgraph-info", "-c", source.name, "-o", str(obj)]
        run = subprocess.run(cmd, cwd=tree, capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        graph = obj.with_suffix(".ci").read_text()
        for caller, callee in re.findall(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"', graph):
            if callee == "__indirect_call":
                indirect.add(source.name)
            else:
                edges.setdefault(caller, set()).add(callee)
    return edges, indirect


def _cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the graph (a path that comes back to its start), or None; iterative depth-first search."""
    state: dict[str, int] = {}  # 1: on the current path, 2: finished
    for root in edges:
        if root in state:
            continue
        path, stack = [root], [iter(sorted(edges.get(root, ())))]
        state[root] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return path[path.index(nxt) :] + [nxt]
            elif nxt not in state:
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(sorted(edges.get(nxt, ()))))
    return None


def test_the_cycle_finder_finds_mutual_recursion():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_no_recursion_in_the_call_graph(tree):
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("-fcallgraph-info needs GCC")
    edges, indirect = _call_graph(tree, gcc)
    assert sum(len(v) for v in edges.values()) > 300  # the graph was read: the core makes hundreds of calls
    assert _cycle(edges) is None, _cycle(edges)
    assert indirect <= INDIRECT_CALLERS, indirect
