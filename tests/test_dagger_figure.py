"""docs/make_dagger_figure.py's rounds figure: with ten runs (twenty legend entries, as
docs/dagger_perceived_scale.png has) the legend lies below the panels, covering none of their area."""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COLUMNS = ("run", "round", "labels", "wall_s", "val_success", "val_collision", "drive_success", "drive_collision")


def _script():
    spec = importlib.util.spec_from_file_location("make_dagger_figure", ROOT / "docs" / "make_dagger_figure.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_rounds_legend_of_ten_runs_covers_no_panel(tmp_path):
    import matplotlib.pyplot as plt

    rounds = tmp_path / "rounds.csv"
    with open(rounds, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(COLUMNS)
        for run in range(10):
            for k in range(4):  # lines across each panel's whole width, where a legend inside would sit on them
                writer.writerow([f"s{run}", k, 4000 * (k + 1), 300 * (k + 1), 0.6 + 0.05 * k + 0.01 * run,
                                 0.3 - 0.07 * k, 0.7, 0.1])
    fig = _script().plot_rounds([str(rounds)], str(tmp_path / "rounds.png"), "turn_perceived")
    try:
        fig.canvas.draw()
        (legend,) = fig.legends
        assert len(legend.get_texts()) == 20
        box = legend.get_window_extent()
        for ax in fig.axes:
            assert not box.overlaps(ax.get_window_extent()), ax.get_xlabel()
        assert (tmp_path / "rounds.png").stat().st_size > 0
    finally:
        plt.close(fig)
