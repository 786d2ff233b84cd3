"""tests/test_continue_run.py's check on CarRacing, whose runs carry more state (return normalizers, the
tracks' generators): the two scripts its long campaign continues, a curator's (plr.py) and a PAIRED-family
one's (paired_bc.py, BiBC). A file of its own, so that its runs and the maze's go to two test workers."""

import pytest
from conftest import f1_track_file
from test_continue_run import CURATOR, check_continued, play

# CarRacing's held-out and validation levels here: the vanilla track and Italy (a track file of it alone, cut to
# 100 frames).
CARRACING = ["--env", "carracing", "--num-envs", "2", "--num-steps", "8", "--num-minibatches", "2", "--update-epochs", "1",
             "--eval-episodes", "1", "--eval-interval", "100", "--checkpoint-interval", "1"]
# (script, env flags, the script's flags, B: the first part's budget in env steps; 2 updates)
CASES = {
    "plr-carracing": ("plr.py", CARRACING, CURATOR, 32),
    "paired_bc-carracing": ("paired_bc.py", CARRACING, ["--bidirectional", "--bc-interval", "1"], 32),
}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    return play(CASES, tmp_path_factory, ["--f1-tracks", f1_track_file(tmp_path_factory.mktemp("tracks"), ["Italy"], "italy", frames=100)])


@pytest.mark.parametrize("case", list(CASES))
def test_a_carracing_run_continued_to_a_longer_budget_equals_one_given_it_from_the_start(finished, case):
    check_continued(finished[case], CASES[case][3])
