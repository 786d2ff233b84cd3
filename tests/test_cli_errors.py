"""Bad command lines in every script: a value of the wrong type or an unknown option is one `error:` line
on stderr and exit status 2, as every other bad input; `--help` still prints the options and exits 0.
Each script's parser runs here, and one bad command line per script runs the script's main block too
(in this process: it stops while parsing), which must end the same way and write nothing."""

from __future__ import annotations

import os
import runpy
import sys

import pytest

import accel
import paired
import paired_bc
import paired_evo
import paired_hient
import plr

SCRIPTS = [plr, accel, paired, paired_hient, paired_bc, paired_evo]
IDS = [script.__name__ for script in SCRIPTS]
BAD = {"wrong type": (["--num-envs", "abc"], ["--num-envs", "abc"]), "unknown option": (["--num-env", "4"], ["--num-env"])}


def parse(script, argv, monkeypatch, capsys):
    """The script's command-line parser on argv: (exit status, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", [script.__file__, *argv])
    with pytest.raises(SystemExit) as exit_info:
        script.parse_command_line()
    out, err = capsys.readouterr()
    return exit_info.value.code, out, err


def assert_one_error_line(status, stderr, names):
    assert status == 2
    assert stderr.startswith("error: ") and len(stderr.strip().splitlines()) == 1, stderr
    assert all(name in stderr for name in names), stderr


@pytest.mark.parametrize("script", SCRIPTS, ids=IDS)
@pytest.mark.parametrize("case", list(BAD))
def test_bad_command_line_is_one_error_line_and_status_2(script, case, monkeypatch, capsys):
    """Catches tyro's error box of many lines reaching the user instead of the one `error:` line."""
    argv, names = BAD[case]
    status, out, err = parse(script, argv, monkeypatch, capsys)
    assert_one_error_line(status, err, names)
    assert out == ""


@pytest.mark.parametrize("script", SCRIPTS, ids=IDS)
def test_help_prints_the_options_and_exits_0(script, monkeypatch, capsys):
    """Catches a parser wrapper that swallows `--help` or turns it into an error."""
    status, out, err = parse(script, ["--help"], monkeypatch, capsys)
    assert status == 0
    assert "--num-envs" in out and "--total-timesteps" in out and err == ""


@pytest.mark.parametrize("script", SCRIPTS, ids=IDS)
def test_script_stops_on_a_wrong_type_with_one_line_and_writes_nothing(script, tmp_path, monkeypatch, capsys):
    """Catches a script whose main block still calls tyro directly (its error box, not one line)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [script.__file__, "--num-envs", "abc"])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(script.__file__, run_name="__main__")
    out, err = capsys.readouterr()
    assert_one_error_line(exit_info.value.code, err, ["--num-envs", "abc"])
    assert out == "" and os.listdir(tmp_path) == []
