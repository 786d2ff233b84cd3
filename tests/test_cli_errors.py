"""The command line of every script. Bad command lines: a value of the wrong type or an unknown option is one `error:` line
on stderr and exit status 2, as every other bad input; `--help` still prints the options and exits 0.
Each script's parser runs here, and one bad command line per script runs the script's main block too
(in this process: it stops while parsing), which must end the same way and write nothing."""

from __future__ import annotations

import dataclasses
import json
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
        script.parse_command_line(script.Args, script.paper_args, script.DEFAULT_DECIDING, script.__doc__)
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


def parsed(script, argv, monkeypatch):
    monkeypatch.setattr(sys, "argv", [script.__file__, *argv])
    return script.parse_command_line(script.Args, script.paper_args, script.DEFAULT_DECIDING, script.__doc__)


def help_text(script, argv, monkeypatch, capsys) -> str:
    """--help's text with the box drawing removed and lines joined, so an option and its default read as one line."""
    status, out, _ = parse(script, [*argv, "--help"], monkeypatch, capsys)
    assert status == 0
    return " ".join(" ".join(line.strip(" │─╰╯╭") for line in out.splitlines()).split())


@pytest.mark.parametrize("script", SCRIPTS, ids=IDS)
@pytest.mark.parametrize("env, num_envs, num_steps", [("maze", 32, 256), ("carracing", 16, 125), ("walker", 16, 2000)])
def test_help_shows_the_chosen_envs_paper_defaults(script, env, num_envs, num_steps, monkeypatch, capsys):
    """`--env E --help` shows E's values, not None, and a parse with no other option gets them."""
    text = help_text(script, ["--env", env], monkeypatch, capsys)
    assert f"(default: {num_envs})" in text.split("--num-envs INT", 1)[1].split("--", 1)[0]
    assert f"(default: {num_steps})" in text.split("--num-steps INT", 1)[1].split("--", 1)[0]
    per_env_options = text.split("--total-timesteps", 1)[1]
    assert "{None}" not in per_env_options and "(default: None)" not in per_env_options
    assert parsed(script, ["--env", env], monkeypatch) == script.paper_args(env)


@pytest.mark.parametrize("script", SCRIPTS, ids=IDS)
def test_env_lists_its_choices_and_booleans_are_plain_flags(script, monkeypatch, capsys):
    text = help_text(script, [], monkeypatch, capsys)
    assert "--env {maze,maze25,carracing,walker}" in text
    assert "--normalize-returns, --no-normalize-returns" in text and "{None,True,False}" not in text


@pytest.mark.parametrize("script, argv, name", [
    (plr, [], "robust_plr"), (plr, ["--no-robust"], "plr"), (plr, ["--replay-prob", "0"], "dr"),
    (paired_bc, [], "paired_bc_hient"), (paired_bc, ["--bidirectional"], "paired_bibc_hient"),
    (paired_evo, [], "paired_evo"), (paired_evo, ["--flexible"], "flexpaired_evo"),
    (paired_evo, ["--bc-coef", "0.01", "--bidirectional", "--student-ent-coef", "0.005"], "paired_evo_bibc_hient"),
    (paired_evo, ["--flexible", "--exp-name", "mine"], "mine"),
])
def test_the_default_experiment_name_includes_the_variant(script, argv, name, monkeypatch):
    """Runs of two variants of one script never share a run-directory name."""
    assert parsed(script, argv, monkeypatch).exp_name == name


def test_a_switch_decides_the_defaults_it_implies(monkeypatch):
    assert parsed(paired_evo, ["--flexible"], monkeypatch).replay_prob == 0.9
    assert parsed(paired_evo, ["--flexible", "--replay-prob", "0.3"], monkeypatch).replay_prob == 0.3
    assert parsed(plr, ["--env", "carracing"], monkeypatch).generator == "sketch"
    assert parsed(plr, ["--env", "carracing", "--replay-prob", "0"], monkeypatch).generator == "random"


@pytest.mark.parametrize("writer, reader", [(plr, paired), (paired_hient, paired), (paired, paired_evo)], ids=lambda m: m.__name__)
def test_resuming_another_scripts_run_is_one_error_line(writer, reader, tmp_path, capsys):
    """A run directory of one script given to another's --resume stops before any work: one `error:` line."""
    saved = {**dataclasses.asdict(writer.paper_args()), "script": os.path.basename(writer.__file__)}
    (tmp_path / "args.json").write_text(json.dumps(saved))
    (tmp_path / "checkpoint.pt").write_bytes(b"")
    with pytest.raises(SystemExit) as exit_info:
        reader.resolve_args(reader.paper_args(resume=str(tmp_path)))
    assert_one_error_line(exit_info.value.code, capsys.readouterr().err, [f"a run of {os.path.basename(writer.__file__)}"])


@pytest.mark.parametrize("script", SCRIPTS, ids=IDS)
def test_eval_episodes_0_is_taken_and_a_negative_count_or_milestones_with_it_refused(script, monkeypatch, capsys):
    """--eval-episodes 0 (no evaluation) passes the script's checks; a negative count, or 0 with --milestones (each
    one an evaluation), is one `error:` line and status 2."""
    assert script.resolve_args(parsed(script, ["--eval-episodes", "0"], monkeypatch)).eval_episodes == 0
    for argv in (["--eval-episodes", "-1"], ["--eval-episodes", "0", "--milestones", "1000"]):
        with pytest.raises(SystemExit) as exit_info:
            script.resolve_args(parsed(script, argv, monkeypatch))
        assert_one_error_line(exit_info.value.code, capsys.readouterr().err, ["--eval-episodes", "--milestones"])
    assert script.resolve_args(parsed(script, ["--eval-episodes", "1", "--milestones", "1000"], monkeypatch)).milestones == (1000,)


@pytest.mark.parametrize("script", SCRIPTS, ids=IDS)
@pytest.mark.parametrize("env, options, names", [
    ("maze", {"num_envs": 30, "num_minibatches": 4}, ["--num-envs 30", "--num-minibatches 4"]),  # an LSTM: by env copies
    ("walker", {"num_envs": 3, "num_steps": 5, "num_minibatches": 2}, ["3 x 5 steps", "--num-minibatches 2"]),  # feed-forward: by steps
    ("maze", {"num_minibatches": 0}, ["--num-minibatches must be positive"]),
])
def test_a_student_batch_that_does_not_split_into_its_minibatches_is_refused(script, env, options, names, capsys):
    """Every script's resolve_args checks the students' minibatch split (envs/runs.py's check_student_minibatches)."""
    with pytest.raises(SystemExit) as exit_info:
        script.resolve_args(script.paper_args(env, **options))
    assert_one_error_line(exit_info.value.code, capsys.readouterr().err, names)
