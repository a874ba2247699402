"""Redraw the paper's figures 2, 3, 7, 8 and 9 from this package's code.

    python -m fuzzyocc.figures --out DIR [--sigma-mm 4] [--shift-mm 10]

writes ``fig2_opdf.png``, ``fig3_bayes_merge.png``, ``fig7_fuzzy_fusion.png``,
``fig8_contradiction.png`` and ``fig9_recovery.png``. Needs matplotlib (the
``plots`` extra); nothing else in the package does.

The set-up follows the paper: one beam line of 1 mm cells, distances in mm.

- Figures 2 and 3 (probabilistic): the sensor at 0 and the surface at 50 mm, as
  in the paper's figure 2. The exact Bayes grid has 4 mm cells (18 of them, so
  2**18 configurations), with a cell centred on the surface.
- Figures 7 to 9 (fuzzy): the surface at distance 0, sigma = 4 mm, and the
  contradictory measurement 10 mm behind it: 2.5 sigma, beyond the 1.5 sigma a
  measurement updates, so it lands in space the first one left unknown
  (occluded), which is the situation the paper's figure 9 discusses. A smaller
  sigma makes the shifted surface an unrelated object; a larger one (above
  6.7 mm) puts it inside the first measurement's occupied band.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from fuzzyocc.bayes import elfes_1d, merge, opdf
from fuzzyocc.engine import FuzzyEngine

__all__ = ["FIGURE_FILES", "main", "write_figures"]

FIGURE_FILES: tuple[str, ...] = (
    "fig2_opdf.png",
    "fig3_bayes_merge.png",
    "fig7_fuzzy_fusion.png",
    "fig8_contradiction.png",
    "fig9_recovery.png",
)

_DPI = 110
_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")


def _figure(ncols: int = 1) -> tuple[Any, list[Any]]:
    try:
        from matplotlib.figure import Figure
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError(
            "fuzzyocc.figures needs matplotlib: pip install 'fuzzyrisk[plots]' (or matplotlib>=3.8)"
        ) from None
    fig = Figure(figsize=(6.4 * ncols, 4.4), dpi=_DPI, layout="constrained")
    axes = [fig.add_subplot(1, ncols, k + 1) for k in range(ncols)]
    return fig, axes


def _style(ax: Any, title: str, xlabel: str, ylabel: str, surfaces_mm: Sequence[float]) -> None:
    """Shared look: probability/risk axis [0, 1], the 0.5 "unknown" level, dashed surfaces, legend."""
    ax.axhline(0.5, color="grey", lw=0.8, ls=":", label="unknown (0.5)")
    label = "measured surface" if len(surfaces_mm) == 1 else "measured surfaces"
    for k, s in enumerate(surfaces_mm):
        ax.axvline(s, color="black", lw=0.8, ls="--", alpha=0.6, label=label if k == 0 else None)
    ax.set_ylim(0.0, 1.0)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)


def _risk_axes(ax: Any, title: str, surfaces_mm: Sequence[float]) -> None:
    _style(ax, title, "distance from the measured surface (mm)", "risk (defuzzified occupancy)", surfaces_mm)


class _BeamLine:
    """Cells along one beam, distances in mm from the first surface, fused with an engine."""

    def __init__(self, engine: FuzzyEngine, sigma_mm: float) -> None:
        self.engine = engine
        self.sigma_mm = sigma_mm
        self.cells_mm = np.arange(-40.0, 31.0)

    def unknown(self) -> np.ndarray:
        return np.tile(self.engine.unknown_state(), (self.cells_mm.size, 1))

    def evidence(self, surface_mm: float) -> np.ndarray:
        return self.engine.fuzzify((self.cells_mm - surface_mm) / self.sigma_mm)

    def fuse(self, state: np.ndarray, surface_mm: float) -> np.ndarray:
        return self.engine.fuse(state, self.evidence(surface_mm))

    def risk(self, state: np.ndarray) -> np.ndarray:
        return self.engine.defuzzify(state)


def _fig2(path: Path) -> None:
    cell_mm, n_cells, surface_mm, sigma_mm = 4.0, 18, 50.0, 4.0
    centres = (np.arange(n_cells) + 0.5) * cell_mm
    exact = elfes_1d(n_cells, cell_mm, surface_mm, sigma_mm)
    x = np.linspace(0.0, n_cells * cell_mm, 500)
    fig, (ax,) = _figure()
    label = f"exact Bayes, all 2^{n_cells} configurations (Elfes)"
    ax.step(centres, exact, where="mid", color=_COLOURS[0], label=label)
    ax.plot(centres, exact, "o", ms=3, color=_COLOURS[0])
    ax.plot(x, opdf(x - surface_mm, sigma_mm), color=_COLOURS[1], label="closed form, eq. 4")
    title = f"Fig. 2: occupancy probability along a beam ({cell_mm:g} mm cells, sigma {sigma_mm:g} mm)"
    _style(ax, title, "distance from the sensor (mm)", "P(cell occupied | reading)", [surface_mm])
    fig.savefig(path)


def _fig3(path: Path, shift_mm: float) -> None:
    surface_mm, sigma_mm = 50.0, 4.0
    x = np.linspace(0.0, 90.0, 901)
    first, shifted = opdf(x - surface_mm, sigma_mm), opdf(x - surface_mm - shift_mm, sigma_mm)
    fig, (left, right) = _figure(2)
    p = np.full_like(x, 0.5)
    for k in range(3):
        p = merge(p, first)
        left.plot(x, p, color=_COLOURS[k], label=f"after {k + 1} consistent measurement{'s' if k else ''}")
    q = merge(merge(np.full_like(x, 0.5), first), first)
    right.plot(x, q, color=_COLOURS[0], label="2 measurements at 50 mm")
    for k in range(3):
        q = merge(q, shifted)
        right.plot(x, q, color=_COLOURS[k + 1], label=f"+ {k + 1} at {surface_mm + shift_mm:g} mm")
    xlabel, ylabel = "distance from the sensor (mm)", "P(cell occupied)"
    _style(left, "Fig. 3a: consistent measurements (Bayes merge, eq. 3)", xlabel, ylabel, [surface_mm])
    title = f"Fig. 3b: contradictory measurements, {shift_mm:g} mm behind"
    _style(right, title, xlabel, ylabel, [surface_mm, surface_mm + shift_mm])
    fig.savefig(path)


def _fig7(path: Path, line: _BeamLine) -> None:
    once = line.fuse(line.unknown(), 0.0)
    twice = line.fuse(once, 0.0)
    fig, (left, right) = _figure(2)
    x = line.cells_mm
    left.plot(x, line.risk(line.evidence(0.0)), color=_COLOURS[0], label="raw measurement, defuzzified")
    left.plot(x, line.risk(once), color=_COLOURS[1], label="fused once into unknown space")
    right.plot(x, line.risk(once), color=_COLOURS[1], alpha=0.5, label="fused once")
    right.plot(x, line.risk(twice), color=_COLOURS[2], label="fused twice (consistent)")
    _risk_axes(left, f"Fig. 7a: one measurement (sigma {line.sigma_mm:g} mm)", [0.0])
    _risk_axes(right, "Fig. 7b: a second consistent measurement", [0.0])
    fig.savefig(path)


def _consistent_twice(line: _BeamLine) -> np.ndarray:
    return line.fuse(line.fuse(line.unknown(), 0.0), 0.0)


def _fig8(path: Path, line: _BeamLine, shift_mm: float) -> None:
    state = _consistent_twice(line)
    fig, (ax,) = _figure()
    x = line.cells_mm
    ax.plot(x, line.risk(state), color=_COLOURS[0], label="two measurements at 0 mm (Fig. 7b)")
    for k in range(2):
        state = line.fuse(state, shift_mm)
        label = f"+ {k + 1} merge{'s' if k else ''} at +{shift_mm:g} mm"
        ax.plot(x, line.risk(state), color=_COLOURS[k + 1], label=label)
    _risk_axes(ax, f"Fig. 8: contradictory measurements shifted +{shift_mm:g} mm", [0.0, shift_mm])
    fig.savefig(path)


def _fig9(path: Path, line: _BeamLine, shift_mm: float) -> None:
    state = _consistent_twice(line)
    state = line.fuse(line.fuse(state, shift_mm), shift_mm)
    fig, (ax,) = _figure()
    x = line.cells_mm
    ax.plot(x, line.risk(state), color=_COLOURS[0], label="perturbed map (Fig. 8)")
    for k in range(3):
        state = line.fuse(state, 0.0)
        ax.plot(x, line.risk(state), color=_COLOURS[k + 1], label=f"+ {k + 1} merge{'s' if k else ''} at 0 mm")
    _risk_axes(ax, "Fig. 9: the perturbed map fused again with the correct measurement", [0.0, shift_mm])
    fig.savefig(path)


def write_figures(
    out_dir: str | Path, *, sigma_mm: float = 4.0, shift_mm: float = 10.0, engine: FuzzyEngine | None = None
) -> list[Path]:
    """Write the five figures as PNG files into ``out_dir`` (created if needed).

    Parameters
    ----------
    out_dir : path
    sigma_mm : float
        Range sigma of the fuzzy figures 7 to 9, mm.
    shift_mm : float
        How far behind the surface the contradictory measurement lies (figures 3, 8, 9), mm.
    engine : FuzzyEngine, optional
        Defaults to :meth:`FuzzyEngine.paper`.

    Returns
    -------
    list of Path
        The files written, in :data:`FIGURE_FILES` order.

    Raises
    ------
    ImportError
        matplotlib is not installed.
    ValueError
        ``sigma_mm`` or ``shift_mm`` not positive and finite.
    """
    for name, value in (("sigma_mm", sigma_mm), ("shift_mm", shift_mm)):
        if not (np.isfinite(value) and value > 0.0):
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    _figure()  # fail early, before creating anything, when matplotlib is missing
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    line = _BeamLine(engine or FuzzyEngine.paper(), sigma_mm)
    paths = [out / name for name in FIGURE_FILES]
    _fig2(paths[0])
    _fig3(paths[1], shift_mm)
    _fig7(paths[2], line)
    _fig8(paths[3], line, shift_mm)
    _fig9(paths[4], line, shift_mm)
    return paths


def _version() -> str:
    """The installed fuzzyrisk's version (this package cannot import ``app.ops.version``)."""
    try:
        return metadata.version("fuzzyrisk")
    except metadata.PackageNotFoundError:
        return "unknown (not installed)"


def main(argv: Sequence[str] | None = None) -> int:
    """Command line entry: ``python -m fuzzyocc.figures --out DIR``."""
    parser = argparse.ArgumentParser(prog="python -m fuzzyocc.figures", description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path, help="directory to write the PNG files into")
    parser.add_argument("--sigma-mm", type=float, default=4.0, help="range sigma of figures 7-9, mm (default 4)")
    parser.add_argument("--shift-mm", type=float, default=10.0, help="shift of the contradictory measurement, mm")
    parser.add_argument("--version", action="version", version=f"%(prog)s (fuzzyrisk) {_version()}")
    args = parser.parse_args(argv)
    try:
        paths = write_figures(args.out, sigma_mm=args.sigma_mm, shift_mm=args.shift_mm)
    except (ImportError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for p in paths:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
