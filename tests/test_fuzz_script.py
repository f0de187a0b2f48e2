"""The long fuzzing run (``scripts/fuzz.py``, 10^6 inputs per decoder and file reader) in short: every target runs a
few hundred inputs with 0 internal errors, 0 hangs and 0 corrupt inputs accepted, and the run's counters are shown to
have power: a decoder that accepts corruption, raises something other than its refusal, or hangs is counted as such.
The properties themselves are pinned by tests/test_protocol_properties.py and tests/test_files_fuzz_properties.py."""

from __future__ import annotations

import threading

import pytest
from scripts_loader import load_script

fuzz = load_script("fuzz.py")

#: Inputs per target here: each generator's branches many times over, under 2 s per target on a loaded machine
#: (the slowest targets, the session reader and ISO-TP, run at ~200-700 inputs/s).
N_INPUTS = {"session_csv": 150, "isotp": 200, "can_stream": 200}
DEFAULT_N = 400


@pytest.mark.parametrize("name", list(fuzz.DECODERS))
def test_every_decoder_and_reader_takes_fuzzed_inputs_without_internal_errors_hangs_or_accepted_corruption(name):
    result = fuzz.run(name, N_INPUTS.get(name, DEFAULT_N), seed=7, hang_s=30.0)
    assert result["inputs"] == N_INPUTS.get(name, DEFAULT_N)
    assert (result["internal_errors"], result["corrupt_accepted"], result["hangs"]) == (0, 0, 0), result


def test_a_block_check_that_passes_corruption_is_counted_as_accepted(monkeypatch):
    monkeypatch.setattr(fuzz.mm, "block_intact", lambda *_args: True)
    result = fuzz.run("modbus_block", 50, seed=1)
    assert result["corrupt_accepted"] == 50 and result["internal_errors"] == 0


def test_a_decoder_raising_anything_but_its_refusal_is_counted_as_an_internal_error(monkeypatch):
    def broken(_data):
        raise KeyError("type")

    monkeypatch.setattr(fuzz, "decode_table", broken)
    result = fuzz.run("param_table", 20, seed=1)
    assert result["internal_errors"] == 20 and result["first_internal_error"] == "KeyError: 'type'"


@pytest.mark.skipif(not hasattr(fuzz.signal, "setitimer"), reason="the hang timer is a POSIX interval timer")
def test_an_input_that_never_returns_is_interrupted_and_counted_as_a_hang(monkeypatch):
    never = threading.Event()  # never set: waiting on it is a decoder that does not return

    def stuck(_data):
        never.wait()

    monkeypatch.setattr(fuzz, "decode_table", stuck)
    result = fuzz.run("param_table", 2, seed=1, hang_s=0.2)
    assert result["hangs"] == 2 and result["inputs"] == 2
