"""Write docs/fit_stages.md: every fit's stages and term weights per budget, as the recipes build
them (softras_cl.fitting.reports.stages). Run after changing a schedule or a weight; a test
fails while the page is out of date."""
from pathlib import Path

from softras_cl.fitting.reports.stages import fit_stages_markdown

PAGE = Path(__file__).resolve().parents[1] / "docs" / "fit_stages.md"

if __name__ == "__main__":
    PAGE.write_text(fit_stages_markdown())
    print(f"wrote {PAGE}")
