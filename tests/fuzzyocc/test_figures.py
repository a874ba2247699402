from pathlib import Path

import pytest
from PIL import Image

from fuzzyocc.figures import FIGURE_FILES, main, write_figures


def test_figures_command_writes_the_five_paper_figures(tmp_path: Path) -> None:
    out = tmp_path / "figs"
    assert main(["--out", str(out)]) == 0  # what `python -m fuzzyocc.figures --out DIR` runs
    assert sorted(p.name for p in out.iterdir()) == sorted(FIGURE_FILES)
    for name in FIGURE_FILES:
        with Image.open(out / name) as image:
            image.verify()  # a complete, well-formed PNG
        with Image.open(out / name) as image:
            assert image.format == "PNG"
            width, height = image.size
            assert width >= 600 and height >= 400, (name, image.size)
            # Not a blank canvas: plotted lines and text give many distinct colours.
            assert len(image.convert("RGB").getcolors(maxcolors=1 << 20) or []) > 50, name


def test_figures_command_refuses_bad_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--out", str(tmp_path / "figs"), "--sigma-mm", "-1"]) == 2
    assert "sigma_mm must be a finite number > 0" in capsys.readouterr().err
    assert not (tmp_path / "figs").exists()


def test_write_figures_refuses_non_positive_shift(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="shift_mm"):
        write_figures(tmp_path, shift_mm=0.0)
