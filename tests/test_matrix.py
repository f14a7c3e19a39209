"""The learner x system matrix driver (hybridctl.reproduce.matrix): its cells, its table and its maps."""

import numpy as np
import pytest

from hybridctl.reproduce import matrix


def test_every_cell_key_round_trips_and_unknown_keys_are_refused():
    assert [matrix.cell_by_key(c.key) for c in matrix.CELLS] == list(matrix.CELLS)
    with pytest.raises(ValueError, match="unknown cell 'acrobot:ppo'; known: acrobot:ssac"):
        matrix.cell_by_key("acrobot:ppo")


def test_shipped_cells_name_checkpoints_that_exist_with_their_training_record():
    for cell in matrix.CELLS:
        if cell.policy is not None:
            record = matrix.training_record(cell.policy)
            assert record["interactions"] > 0 and record["train_wall_time_s"] > 0
            assert cell.policy in cell.controller


def test_fine_tuned_cells_name_committed_runs_of_the_shipped_swing_ups():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    tuned = {c.key: c for c in matrix.CELLS if c.finetune is not None}
    assert set(tuned) == {f"{s}:{row}" for s in matrix.SYSTEMS for row in ("ssac-fine-tuned", "apg-fine-tuned")}
    for cell in tuned.values():
        report = matrix.io.read_json(root / cell.finetune / "report.json")
        assert report["env_steps"] > 0 and (root / cell.finetune / "final" / "model.pt").is_file()
        # the fine-tuning started from the row above's shipped checkpoint
        learned = matrix.cell_by_key(f"{cell.system}:" + ("ssac" if cell.row == "SSAC fine-tuned" else "apg-family"))
        assert report["command"].split("--policy ")[1].split()[0] == learned.controller


def test_the_acrobot_map_spans_every_angle_unless_near_hanging_down():
    axes, ranges = matrix.map_ranges("acrobot")
    assert axes == (0, 1)
    assert ranges[0] == pytest.approx((-np.pi / 2 - 0.3, -np.pi / 2 + 0.3)) and ranges[1] == pytest.approx((-0.3, 0.3))
    assert matrix.map_ranges("cartpole") == (None, None)


def test_markdown_table_shows_fraction_interactions_wall_time_and_a_missed_aim():
    record = {"cells": {
        "acrobot:apg-family": {"balanced_fraction": 0.5, "balanced_count": 60, "grid": 11, "interactions": 3.0e7, "train_wall_time_s": 600.0, "goal": 0.9},
        "cartpole:trajopt": {"balanced_fraction": 1.0, "goal": None},
        "acrobot:ssac": {"note": "nothing shipped"},
    }}
    table = matrix.markdown_table(record).splitlines()
    assert table[0] == "| learner | acrobot | cart-pole | double cart-pole |"
    assert len(table) == 2 + len(matrix.ROWS)
    apg = next(line for line in table if line.startswith("| APG family"))
    assert "60/121 (50%) (3.0e+07 steps, 10 min) (aim 90%)" in apg
    trajopt = next(line for line in table if line.startswith("| trajopt"))
    assert trajopt == "| trajopt | - | 100% | - |"
    assert next(line for line in table if line.startswith("| SSAC")) == "| SSAC | - | - | - |"


def test_short_of_aim_lists_the_cells_that_miss_their_aim_with_their_notes():
    record = {"cells": {"acrobot:apg-family": {"balanced_fraction": 0.95, "note": "met"},
                        "double_cartpole:ssac": {"balanced_fraction": 0.5, "note": "tried A and B"}}}
    text = matrix.short_of_aim(record)
    assert "acrobot, APG family" not in text
    note = matrix.cell_by_key("double_cartpole:ssac").note
    assert f"**double_cartpole, SSAC** (aim 80%): 50% of the map. {note}" in text
    assert "**double_cartpole, APG family** (aim 80%): nothing shipped." in text


def test_a_cell_without_a_controller_keeps_its_note_and_maps_nothing():
    cell = matrix.Cell("double_cartpole", "energy", None, None, "none for two poles")
    record = matrix.measure(cell)
    assert record["controller"] is None and "balanced_fraction" not in record and record["note"]


def test_an_attempt_needs_a_finished_run_folder(tmp_path):
    with pytest.raises(ValueError, match="no final/config.json"):
        matrix.attempt("acrobot:apg-family", tmp_path)
    with pytest.raises(ValueError, match="unknown cell"):
        matrix.attempt("acrobot:nope", tmp_path)


def test_the_readme_and_the_docs_page_show_the_recorded_matrix():
    """One source: the README's table is the record's (``matrix table`` rewrites table.md from it)."""
    from pathlib import Path

    from hybridctl import io

    root = Path(__file__).resolve().parents[1]
    record = io.read_json(root / "results" / "matrix" / "matrix.json")
    table = matrix.markdown_table(record)
    assert table in (root / "README.md").read_text()
    assert (root / "results" / "matrix" / "table.md").read_text().strip() == table
    assert '--8<-- "results/matrix/table.md"' in (root / "docs" / "matrix.md").read_text()


def test_update_readme_replaces_only_the_table_after_the_marker(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n\n{matrix.README_MARKER}\n| old |\n|---|\n\n## Next\ntext\n")
    assert matrix.update_readme("| new |\n|---|", readme)
    assert readme.read_text() == f"intro\n\n{matrix.README_MARKER}\n| new |\n|---|\n\n## Next\ntext\n"
    assert not matrix.update_readme("| x |", tmp_path / "missing.md")


def test_a_second_driver_writing_the_matrix_is_refused_at_once(tmp_path, monkeypatch):
    from hybridctl import io

    monkeypatch.setattr(matrix, "OUT", tmp_path / "matrix")
    monkeypatch.setattr(matrix, "README", tmp_path / "README.md")     # never the checkout's README
    import multiprocessing
    ready, release = multiprocessing.Event(), multiprocessing.Event()

    def hold():
        with io.locked_folder(tmp_path / "matrix", "results/matrix"):
            ready.set()
            release.wait(30)

    holder = multiprocessing.get_context("fork").Process(target=hold)
    holder.start()
    try:
        assert ready.wait(30)
        with pytest.raises(io.RunFolderError, match="locked by pid"):
            matrix.run(["double_cartpole:energy"])
    finally:
        release.set()
        holder.join(30)
    assert matrix.run(["double_cartpole:energy"])["cells"]["double_cartpole:energy"]["controller"] is None
