"""docs/fit_stages.md is what fitting.reports.stages makes of the recipes now: a changed schedule or
weight without the page regenerated (scripts/write_fit_stages.py) fails here."""
from pathlib import Path

from softras_cl.fitting.recipes.face_settings import BUDGETS
from softras_cl.fitting.reports.stages import fit_stages_markdown, stage_rows
from softras_cl.fitting.solver import Stage

PAGE = Path(__file__).resolve().parents[3] / "docs" / "fit_stages.md"


def test_the_page_is_current():
    assert PAGE.read_text() == fit_stages_markdown(), "run: python scripts/write_fit_stages.py"


def test_a_row_holds_the_stage():
    row = stage_rows([Stage("photo-1", ("id", "exp"), dict(photo=100.0, landmarks=0.25), sigma=1e-4, gamma=3e-3,
                            max_iters=40)])
    assert row == [("photo-1", "id, exp", "0.0001", "0.003", "40", "photo 100, landmarks 0.25")]


def test_the_page_shows_every_budgets_evaluations():
    page = fit_stages_markdown()
    for budget, schedule in BUDGETS.items():
        assert f"### --budget {budget}" in page
        assert f"| landmarks | rotation, translation, focal, id, exp |  |  | {schedule['landmark_iters']} |" in page
