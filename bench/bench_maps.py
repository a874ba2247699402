"""Map quality on real buildings, ours against OctoMap in the same run.

    python3 dev.py bench maps [--data DIR] [--logs a,b] [--engine PRESET] [--quick] [--jobs N] [--reproducible-plans]
    python -m bench.bench_maps ...                                  (from the repository root)

For every CARMEN log in ``DIR/carmen`` (``--data DIR``, ``bench/_data.py``: default ``../shared/data`` beside
the repository where it exists, else the repository's ``tests/data``; ``--logs``: names such as ``orebro,fhw``):

1. held-out beams (``bench/_logmaps.py``): fuse 9 scans of every 10 into our ``FuzzyMap``
   (``--engine``, default ``fuzzyocc.presets.DEFAULT_PRESET``), ``BayesMap`` and OctoMap (its
   default sensor model, same scans and resolution); march each held-out hit beam to the first
   cell at or above risk 0.6 (OctoMap: ``castRay``); the fraction within 2 cells of the measured
   range, the median absolute error, the fractions too early (> 2 cells short), too late, and
   with no surface found;
2. a dynamic obstacle (``bench/_dynamic.py``): a 0.4 m box seen in 3 scans, then gone; the
   unmodified scans until each map clears it (median / max over 5 placements, capped at 50);
3. a plan audit (``bench/_plan_audit.py``): grid and RRTstar plans between far-apart poses the
   robot drove, on our map's risk, each path's clearance from OctoMap's occupied cells;
4. the wall seconds each model took to fuse the training scans (same process).

One table per log with the targets met and not met under it, then a summary. ``--quick``: the
first 120 scans of each log, 3 obstacles, 2 plan pairs (what the CI test runs on one log).
``--reproducible-plans``: RRTstar on a fixed iteration count instead of 1 s (a seeded plan that
the clock ends, as on a loaded machine, may differ between runs; the CI test uses this).
Logs run in ``--jobs`` processes (default: 2, or the cores there are), printed in name order.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import platform
import statistics
import sys
import time
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from bench import _data, _dynamic, _logmaps, _plan_audit
from bench._dynamic import Trial
from bench._logmaps import Score
from bench._plan_audit import PlanCheck
from fuzzyocc import BayesMap, FuzzyMap, GridSpec, LaserScan
from fuzzyocc.presets import DEFAULT_PRESET, PRESETS, preset

QUICK_SCANS = 120
QUICK_TRIALS = 3
QUICK_PAIRS = 2
OURS = "FuzzyMap"
MODELS = ("FuzzyMap", "BayesMap", "OctoMap")
# target slack, in points of the held-out beams
NONE_SLACK = 0.01
EARLY_SLACK = 0.02


@dataclass
class LogReport:
    """Every figure of one log."""

    name: str
    engine: str
    scans: int
    fused: int
    beams: int
    shape: tuple[int, ...]
    resolution: float
    scores: dict[str, Score]
    fusion_s: dict[str, float]
    trials: list[Trial]
    plans: list[PlanCheck]
    seconds: float = 0.0
    phases: dict[str, float] = field(default_factory=dict)  # wall seconds of each step


_warm = False


def _warm_up(engine_name: str) -> None:
    """Compile (or load) the numba kernels on a tiny map, so no fusion time below includes the compiler."""
    global _warm
    if _warm:
        return
    spec = GridSpec(origin=(0.0, 0.0), size=(2.0, 2.0), resolution=0.05)
    scan = LaserScan(pose=(1.0, 1.0, 0.0), angle_min=-1.0, angle_increment=0.1, ranges=np.full(21, 0.8),
                     range_min=0.01, range_max=5.0)
    for m in (FuzzyMap(spec, engine=preset(engine_name)), BayesMap(spec)):
        m.integrate_batch([scan])
        m.risk()
    beams = _logmaps.held_out_beams([scan])
    _logmaps.predicted_ranges(np.zeros(spec.shape, np.float32), spec, beams)
    _warm = True


def evaluate_log(path: Path, engine_name: str = DEFAULT_PRESET, scan_limit: int | None = None,
                 trials: int = _dynamic.TRIALS, pairs: int = _plan_audit.PAIRS,
                 reproducible_plans: bool = False) -> LogReport:
    """All figures of one log for ``FuzzyMap`` (preset ``engine_name``), ``BayesMap`` and OctoMap.

    ``reproducible_plans``: RRTstar runs ``_plan_audit.FIXED_ITERATIONS`` iterations instead of
    1 s, so its paths do not depend on the machine's load (the CI test).
    """
    started = time.perf_counter()
    _warm_up(engine_name)
    name = _logmaps.log_name(path)
    scans = _logmaps.load(path)[:scan_limit]
    spec = _logmaps.grid_for(scans)
    fused, held = _logmaps.split(scans)
    beams = _logmaps.held_out_beams(held)

    fusion_s: dict[str, float] = {}
    t = time.perf_counter()
    fuzzy = FuzzyMap(spec, engine=preset(engine_name))
    _logmaps.fuse(fuzzy, fused)
    risk = fuzzy.risk()
    fusion_s["FuzzyMap"] = time.perf_counter() - t
    t = time.perf_counter()
    bayes = BayesMap(spec)
    _logmaps.fuse(bayes, fused)
    bayes_risk = bayes.risk()
    fusion_s["BayesMap"] = time.perf_counter() - t
    t = time.perf_counter()
    tree = _logmaps.octomap_tree(spec, fused)
    fusion_s["OctoMap"] = time.perf_counter() - t

    phases = {"load and fusion": time.perf_counter() - started}
    t = time.perf_counter()
    scores = {
        "FuzzyMap": _logmaps.score(_logmaps.predicted_ranges(risk, spec, beams), beams.ranges, spec.resolution),
        "BayesMap": _logmaps.score(_logmaps.predicted_ranges(bayes_risk, spec, beams), beams.ranges, spec.resolution),
        "OctoMap": _logmaps.score(_logmaps.octomap_predicted(tree, spec, beams), beams.ranges, spec.resolution),
    }
    octo_occupied = _logmaps.octomap_occupied(tree, spec)
    phases["held-out"] = time.perf_counter() - t
    t = time.perf_counter()
    obstacle_trials = _dynamic.run_trials(fused, spec, fuzzy, bayes, tree, octo_occupied, trials=trials)
    phases["obstacle"] = time.perf_counter() - t
    del bayes, bayes_risk, tree
    t = time.perf_counter()
    poses = np.array([s.pose[:2] for s in scans])
    limits = ({"time_limit": _plan_audit.FIXED_TIME_LIMIT, "max_iterations": _plan_audit.FIXED_ITERATIONS}
              if reproducible_plans else {})
    plans = _plan_audit.audit(risk, fuzzy.observed(), spec, poses, octo_occupied, pairs=pairs, **limits)
    phases["plans"] = time.perf_counter() - t
    return LogReport(name=name, engine=engine_name, scans=len(scans), fused=len(fused), beams=int(beams.ranges.size),
                     shape=spec.shape, resolution=spec.resolution, scores=scores, fusion_s=fusion_s,
                     trials=obstacle_trials, plans=plans, seconds=time.perf_counter() - started, phases=phases)


# ------------------------------------------------------------------ targets
@dataclass(frozen=True)
class Target:
    """One map-quality target on one log: met or not, and the numbers that say so."""

    name: str
    met: bool
    detail: str


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def _cm(x: float) -> str:
    return "inf" if math.isinf(x) else f"{100 * x:.1f} cm"


def _clear_count(n: int) -> str:
    return f">{_dynamic.CAP}" if n > _dynamic.CAP else str(n)


def targets(rep: LogReport) -> list[Target]:
    """The issue's targets for our map against OctoMap's figures of the same run."""
    ours, octo = rep.scores[OURS], rep.scores["OctoMap"]
    out = [
        Target("within 2 cells", ours.within >= octo.within,
               f"{_pct(ours.within)} vs OctoMap {_pct(octo.within)} (>=)"),
        Target("no surface", ours.none <= octo.none + NONE_SLACK,
               f"{_pct(ours.none)} vs OctoMap {_pct(octo.none)} (<= + 1 pt)"),
        Target("too early", ours.early <= octo.early + EARLY_SLACK,
               f"{_pct(ours.early)} vs OctoMap {_pct(octo.early)} (<= + 2 pt)"),
        Target("median error", ours.median_error <= octo.median_error,
               f"{_cm(ours.median_error)} vs OctoMap {_cm(octo.median_error)} (<=)"),
    ]
    t = rep.trials
    mine = [x.scans_to_clear[OURS] for x in t]
    theirs = [x.scans_to_clear["OctoMap"] for x in t]
    missed = sum(x.seen["OctoMap"] and not x.seen[OURS] for x in t)
    detail = (f"scans per obstacle {[_clear_count(n) for n in mine]} vs OctoMap {[_clear_count(n) for n in theirs]}"
              " (<= on each)").replace("'", "")
    if missed:
        detail += f"; ours never marked {missed} obstacle(s) OctoMap marked"
    behind = [f"#{k + 1} ({x.no_returns} of {x.beams} beams)" for k, x in enumerate(t) if x.no_returns]
    if behind:
        detail += "; no-returns behind the box at " + ", ".join(behind)
    if not t:
        detail = "no obstacle could be placed"
    out.append(Target("obstacle cleared", bool(t) and not missed and all(a <= b for a, b in zip(mine, theirs)), detail))
    paths = [c for c in rep.plans if c.has_path]
    bad = [c for c in paths if not c.clear(rep.resolution)]
    least = min((c.clearance for c in paths), default=math.nan)
    floor = _plan_audit.ROBOT_RADIUS - rep.resolution
    out.append(Target("plans clear of OctoMap", bool(paths) and not bad,
                      f"{len(bad)} of {len(paths)} paths closer than {floor:.2f} m; least clearance {least:.2f} m"
                      if paths else f"no path to audit ({len(rep.plans)} plans asked)"))
    return out


# ------------------------------------------------------------------ printing
def _plans_cell(rep: LogReport) -> str:
    clear = sum(c.clear(rep.resolution) for c in rep.plans)
    return f"{clear}/{len(rep.plans)}"


def table(rep: LogReport) -> str:
    """The log's markdown table, its plan line and its target line."""
    lines = [
        f"### {rep.name}: {rep.scans} scans ({rep.fused} fused, {rep.beams:,} held-out hit beams), "
        f"{rep.shape[0]} x {rep.shape[1]} cells of {rep.resolution} m, engine {rep.engine!r} ({rep.seconds:.0f} s: "
        + ", ".join(f"{k} {v:.0f}" for k, v in rep.phases.items()) + ")",
        "",
        "| model | within 2 cells | median error | too early | too late | no surface | scans to clear (median / max) "
        "| plans clear / asked | fusion s (vs OctoMap) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    octo_s = rep.fusion_s["OctoMap"]
    for model in MODELS:
        label = f"{model} ({rep.engine})" if model == OURS else model
        plans = _plans_cell(rep) if model == OURS else "-"
        lines.append(f"| {label} | " + " | ".join(rep.scores[model].row())
                     + f" | {_dynamic.summary(rep.trials, model)} | {plans} "
                     f"| {rep.fusion_s[model]:.1f} ({rep.fusion_s[model] / octo_s:.2f}x) |")
    lines.append("")
    lines.append(_plan_line(rep))
    tg = targets(rep)
    lines.append("")
    lines.append("targets: " + "; ".join(f"{x.name} {'met' if x.met else '**NOT met**'} ({x.detail})" for x in tg))
    return "\n".join(lines)


def _plan_line(rep: LogReport) -> str:
    if not rep.plans:
        return "plans: no pair of driven poses far enough apart and free on our map"
    parts = []
    for planner in _plan_audit.PLANNERS:
        mine = [c for c in rep.plans if c.planner == planner]
        if mine:
            extra = sum(c.status == "approximate" for c in mine)
            close = sum(c.has_path and not c.clear(rep.resolution) for c in mine)
            parts.append(f"{planner}: exact {sum(c.found for c in mine)}/{len(mine)}"
                         + (f" (+{extra} approximate)" if extra else "") + f", {close} too close")
    ratios = []
    for k in sorted({c.pair for c in rep.plans}):
        by = {c.planner: c for c in rep.plans if c.pair == k}
        if all(p in by and by[p].found for p in ("RRTstar", "grid")):
            ratios.append(by["RRTstar"].cost / by["grid"].cost)
    apart = [c.apart for c in rep.plans if c.planner == _plan_audit.PLANNERS[0]]
    text = f"plans: {len(apart)} pairs {min(apart):.0f}-{max(apart):.0f} m apart; " + "; ".join(parts)
    if ratios:
        text += (f"; RRTstar cost / grid optimum's: median {statistics.median(ratios):.3f} "
                 f"({min(ratios):.3f}-{max(ratios):.3f}, {len(ratios)} pairs)")
    from planning.query import CLOCK_NOTE  # OMPL: loaded here only, the workers have it already

    clocked = sum(CLOCK_NOTE in c.note for c in rep.plans)
    if clocked:
        text += f"; {clocked} seeded solve(s) ended by the clock, not the seeded budget"
    return text


def summary_table(reports: list[LogReport]) -> str:
    names = [t.name for t in targets(reports[0])] if reports else []
    lines = ["| log | " + " | ".join(names) + " | all met |", "|---" * (len(names) + 2) + "|"]
    for rep in reports:
        tg = targets(rep)
        cells = ["met" if x.met else "**no**" for x in tg]
        lines.append(f"| {rep.name} | " + " | ".join(cells) + f" | {'yes' if all(x.met for x in tg) else '**no**'} |")
    return "\n".join(lines)


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _run_one(path: str, engine: str, limit: int | None, trials: int, pairs: int, reproducible: bool) -> LogReport:
    rep = evaluate_log(Path(path), engine, limit, trials, pairs, reproducible)
    sys.stdout.flush()  # in-process (--jobs 1): keep the tables and this progress line in order
    steps = ", ".join(f"{k} {v:.0f}" for k, v in rep.phases.items())
    print(f"bench maps: {rep.name} done in {rep.seconds:.0f} s ({steps})", file=sys.stderr, flush=True)
    return rep


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench maps", description=__doc__.split("\n\n")[0])
    _data.add_option(ap)
    ap.add_argument("--logs", help="comma-separated log names (e.g. orebro,fhw); default: every log there")
    ap.add_argument("--engine", default=DEFAULT_PRESET, help=f"our map's engine preset (default {DEFAULT_PRESET!r})")
    ap.add_argument("--quick", action="store_true",
                    help=f"first {QUICK_SCANS} scans of each log, {QUICK_TRIALS} obstacles, {QUICK_PAIRS} plan pairs")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="logs evaluated at once (processes)")
    ap.add_argument("--reproducible-plans", action="store_true",
                    help=f"RRTstar runs {_plan_audit.FIXED_ITERATIONS:,} iterations instead of "
                         f"{_plan_audit.TIME_LIMIT:g} s: the same paths whatever the machine's load")
    args = ap.parse_args(argv)
    _data.use(args)
    if args.engine not in PRESETS:
        ap.error(f"no engine preset named {args.engine!r}; the presets are {sorted(PRESETS)}")
    paths = _logmaps.log_paths()
    if args.logs:
        wanted = [w.strip() for w in args.logs.split(",") if w.strip()]
        known = {_logmaps.log_name(p): p for p in paths}
        unknown = [w for w in wanted if w not in known]
        if unknown:
            ap.error(f"unknown log(s) {unknown}; the logs are {sorted(known)}")
        paths = [known[w] for w in wanted]
    paths = sorted(paths, key=_logmaps.log_name)
    limit, trials, pairs = ((QUICK_SCANS, QUICK_TRIALS, QUICK_PAIRS) if args.quick
                            else (None, _dynamic.TRIALS, _plan_audit.PAIRS))
    jobs = max(1, min(args.jobs, len(paths)))

    started = time.perf_counter()
    print(f"# bench maps, {datetime.now().astimezone():%Y-%m-%d %H:%M %Z}")
    print()
    print(f"machine: {_cpu()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; Python "
          f"{platform.python_version()}; {jobs} process(es), one log each at a time (fusion seconds: the three "
          "models in turn in the log's process)")
    scope = f"QUICK: first {limit} scans, {trials} obstacles, {pairs} plan pairs" if args.quick else "full logs"
    print(f"engine: {args.engine!r} (default preset: {DEFAULT_PRESET!r}); {scope}")
    print("held-out: every 10th scan's hit beams, first cell at risk >= 0.6 (OctoMap: castRay, isNodeOccupied); "
          "within = |error| <= 2 cells; early / late = more than 2 cells short / long; no surface = none found; "
          "median |error| with no surface as infinite")
    rrt = (f"{_plan_audit.FIXED_ITERATIONS:,} iterations" if args.reproducible_plans
           else f"{_plan_audit.TIME_LIMIT:g} s")
    print(f"obstacle: {_dynamic.BOX_M} m box seen in {_dynamic.SEEN} scans then gone; unmodified scans until "
          f"cleared (cap {_dynamic.CAP}); plans: grid and RRTstar ({rrt}, seeded), radius "
          f"{_plan_audit.ROBOT_RADIUS} m, max_risk {_plan_audit.MAX_RISK}; clear = path >= radius - 1 cell "
          "from OctoMap's occupied cells")
    print(flush=True)

    reports: list[LogReport] = []
    args_of = {p: (str(p), args.engine, limit, trials, pairs, args.reproducible_plans) for p in paths}
    if jobs == 1:
        for p in paths:
            reports.append(_run_one(*args_of[p]))
            print(table(reports[-1]), end="\n\n", flush=True)
    else:
        with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            # the largest logs first, so that the last to finish is a small one
            order = sorted(paths, key=lambda p: p.stat().st_size, reverse=True)
            futures: dict[Path, Future[LogReport]] = {p: pool.submit(_run_one, *args_of[p]) for p in order}
            for p in paths:
                reports.append(futures[p].result())
                print(table(reports[-1]), end="\n\n", flush=True)

    print("## Summary (our map against OctoMap, same run)")
    print()
    print(summary_table(reports))
    print()
    every = all(x.met for r in reports for x in targets(r))
    print(f"every target met on every log: {'YES' if every else 'NO'}")
    print(f"run time: {time.perf_counter() - started:.0f} s for {len(reports)} log(s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
