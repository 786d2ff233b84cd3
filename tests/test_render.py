"""curves.png: one panel per quantity on its own axis, readable labels, the smoothing stated, rates on
[0, 1], and "nan" cells (no episode finished) drawn as gaps rather than as zeros."""

import numpy as np
import pytest

from envs import render
from envs.render import rolling_mean, save_curves, split_by_quantity

# The PAIRED scripts' groups on the maze.
PAIRED_PANELS = [
    ("returns", ["protagonist_return", "antagonist_return", "regret"]),
    ("validation solved rate", ["val_solved_rate"]),
    ("entropy", ["protagonist_entropy", "antagonist_entropy", "teacher_entropy"]),
    ("level complexity", ["walls", "passable", "path_length"]),
]


def test_each_quantity_gets_its_own_panel():
    drawn = split_by_quantity(PAIRED_PANELS)
    assert [title for title, _, _ in drawn] == [
        "return", "regret estimate", "validation solved rate", "student policy entropy", "teacher policy entropy",
        "walls per level", "share of levels with a path to the goal", "shortest path length (170: no path)"]
    assert drawn[0][2] == ["protagonist_return", "antagonist_return"]  # both students' returns on one axis
    assert split_by_quantity([("odd", ["some_new_column"])]) == [("odd", "some new column", ["some_new_column"])]


def test_rolling_mean_over_updates_keeps_gaps():
    updates = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    values = np.array([1.0, 3.0, np.nan, 5.0, 7.0])
    smoothed = rolling_mean(updates, values, window=2)
    assert np.isnan(smoothed[2])
    assert smoothed[[0, 1, 3, 4]] == pytest.approx([1.0, 2.0, 5.0, 6.0])  # update 4: update 3 had no value
    sparse = rolling_mean(np.array([10.0, 20.0, 30.0]), np.array([0.0, 1.0, 2.0]), window=10)
    assert sparse == pytest.approx([0.0, 1.0, 2.0])  # a value logged every 10 updates is not averaged


def test_save_curves_writes_one_panel_per_quantity_with_gaps_and_an_empty_column(tmp_path, monkeypatch):
    header = "update,env_steps,protagonist_return,antagonist_return,regret,val_solved_rate,protagonist_entropy," \
             "antagonist_entropy,teacher_entropy,walls,passable,path_length"
    lines = [header]
    for update in range(1, 121):
        returned = "nan" if 40 <= update < 50 else f"{update / 200:.3f}"  # no episode finished for 10 updates
        validated = "0.5" if update % 20 == 0 else ""  # logged every 20 updates only
        lines.append(f"{update},{update * 8192},{returned},{returned},0.1,{validated},1.9,1.8,5.0,30,0.9,")  # path_length never
    csv_path = tmp_path / "metrics.csv"
    csv_path.write_text("\n".join(lines) + "\n")
    figures = []
    close = render.plt.close
    monkeypatch.setattr(render.plt, "close", lambda fig: (figures.append(fig), close(fig)))
    png = tmp_path / "curves.png"
    save_curves(str(csv_path), str(png), PAIRED_PANELS)
    assert png.read_bytes().startswith(b"\x89PNG")
    (figure,) = figures
    panels = [ax for ax in figure.axes if ax.axison]
    assert len(panels) == len(split_by_quantity(PAIRED_PANELS)) == 8
    by_title = {ax.get_title(): ax for ax in panels}
    assert by_title["validation solved rate"].get_ylim() == (0, 1)
    assert by_title["share of levels with a path to the goal"].get_ylim() == (0, 1)
    smoothed = [line for line in by_title["return"].get_lines() if line.get_label() == "protagonist"][0]
    assert np.isnan(smoothed.get_ydata()[39:49]).all() and np.isfinite(smoothed.get_ydata()[:39]).all()
    assert any("mean over the last 2 updates" in text.get_text() for text in figure.texts)  # 120 updates / 50
    assert [t.get_text() for t in by_title["shortest path length (170: no path)"].texts] == ["not logged"]
