"""The option sweep (``scripts/cli_sweep.py``: every option of every quick command set to each of 12 values that break
programs) in short: three commands that cover the three kinds of option (a link, numbers, files), every case a
success or a one-line refusal. The whole sweep (15 commands, 1,140 cases) is ``python scripts/cli_sweep.py``."""

from __future__ import annotations

from scripts_loader import load_script


def _load_sweep():
    return load_script("cli_sweep.py")


def test_every_option_of_the_link_number_and_file_commands_is_taken_or_refused_in_one_line():
    n, failures = _load_sweep().sweep(["params", "costs", "import-can"], hang_s=60.0)
    assert failures == []
    assert n >= 5 * 12  # every option of the three, each with every odd value (measured: 72 cases)


def test_the_sweep_reports_an_internal_error(monkeypatch):
    sweep = _load_sweep()
    import hostlink.api as api

    def broken(*_args):
        raise KeyError("boom")

    monkeypatch.setattr(api, "cost_table_text", broken)  # what `hostlink costs` calls
    n, failures = sweep.sweep(["costs"], hang_s=60.0)
    # every case whose options parse reaches run() and is reported (the others argparse refused in one line)
    assert failures and len(failures) < n and all("internal error: KeyError" in f["problem"] for f in failures)
