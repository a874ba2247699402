"""The paper's n-input merge against the ray caster's "most occupied-ward beam wins", on real logs.

    python3 dev.py bench nmerge [--data DIR] [--logs a,b] [--engine PRESET]

The held-out protocol of ``bench_maps`` (fuse 9 scans of every 10, march every held-out hit beam
to the first cell at risk >= 0.6), for the same engine with the beams of one scan that reach a
cell combined two ways: one evidence per cell and scan, the most occupied-ward (what
``FuzzyMap`` does), or all of them at once with ``fuzzyocc.nmerge.merge_n`` (the paper's
n-dimensional rule table); OctoMap beside them, same run. The n-input maps are built in Python
over per-beam casts (``bench/_nmerge_maps.py``), so their seconds are not comparable.
"""

from __future__ import annotations

import argparse
import time

from bench import _data, _logmaps
from bench._nmerge_maps import nmerge_risk
from fuzzyocc import FuzzyMap
from fuzzyocc.presets import DEFAULT_PRESET, preset


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _data.add_option(ap)
    ap.add_argument("--logs", help="comma-separated log names (e.g. orebro,fhw); default: every log there")
    ap.add_argument("--engine", default=DEFAULT_PRESET, help=f"engine preset (default {DEFAULT_PRESET!r})")
    args = ap.parse_args(argv)
    _data.use(args)
    paths = _logmaps.log_paths()  # before any output: a missing data directory ends the run here
    wanted = set(args.logs.split(",")) if args.logs else None
    engine = preset(args.engine)
    print(f"engine {args.engine!r}; held-out hit beams: within 2 cells, median error, too early, too late, no surface")
    print("| log | merge | within 2 cells | median error | too early | too late | no surface |")
    print("|---|---|---|---|---|---|---|")
    started = time.perf_counter()
    for path in paths:
        name = _logmaps.log_name(path)
        if wanted and name not in wanted:
            continue
        scans = _logmaps.load(path)
        spec = _logmaps.grid_for(scans)
        fused, held = _logmaps.split(scans)
        beams = _logmaps.held_out_beams(held)
        ours = FuzzyMap(spec, engine=engine)
        _logmaps.fuse(ours, fused)
        rows = {
            "most occupied-ward wins (FuzzyMap)": ours.risk(),
            "n-input merge": nmerge_risk(spec, fused, engine),
        }
        for label, risk in rows.items():
            score = _logmaps.score(_logmaps.predicted_ranges(risk, spec, beams), beams.ranges, spec.resolution)
            print(f"| {name} | {label} | " + " | ".join(score.row()) + " |", flush=True)
        tree = _logmaps.octomap_tree(spec, fused)
        octo = _logmaps.score(_logmaps.octomap_predicted(tree, spec, beams), beams.ranges, spec.resolution)
        print(f"| {name} | OctoMap | " + " | ".join(octo.row()) + " |", flush=True)
    print(f"run time: {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
