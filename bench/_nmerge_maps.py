"""Maps of a log whose scans are merged cell by cell with the n-input merge (``fuzzyocc.nmerge``).

The same beams, sigmas and engine as ``FuzzyMap``; only how the beams of one scan that reach a
cell are combined differs: all of them at once (the paper's n-dimensional table) instead of the
ray caster's "the most occupied-ward beam wins". A dense state array, no block storage: the
risk is what a FuzzyMap would hold for the same updates (FuzzyMap is bit-identical to dense
fusion, ``tests/fuzzyocc/test_blocks.py``).
"""

from __future__ import annotations

import numpy as np

from fuzzyocc import FuzzyEngine, FuzzyMap, GridSpec, LaserScan, SensorModel
from fuzzyocc.nmerge import merge_n
from fuzzyocc.raycast import cast_rays


def nmerge_risk(spec: GridSpec, scans: list[LaserScan], engine: FuzzyEngine) -> np.ndarray:
    """Risk of ``spec.shape`` after fusing ``scans`` in order, each with the n-input merge per cell."""
    probe = FuzzyMap(GridSpec(origin=spec.origin, size=(spec.resolution,) * spec.ndim,
                              resolution=spec.resolution), SensorModel(), engine)
    state = np.tile(engine.unknown_state(), (spec.num_cells, 1))
    half_cell = 0.5 * spec.resolution
    for scan in scans:
        rays = probe._rays_of(scan)  # the engine's own reading of the beams (no-returns in context)
        n = rays.ranges.size
        if n == 0:
            continue
        sigma = np.maximum(probe.sensor.sigma(rays.ranges, scan.registration_sigma) * probe._grazing(rays), half_cell)
        extent = engine.occupied_extent
        cast = cast_rays(spec, np.repeat(rays.origin[None, :], n, axis=0), rays.directions,
                         t_end=np.where(rays.hit, rays.ranges + extent * sigma, rays.ranges),
                         measured=np.where(rays.hit, rays.ranges, np.nan), sigma=sigma,
                         ray_offsets=np.arange(n + 1), unknown_from=extent)
        keep = np.isfinite(cast.distance_sigmas)  # -inf: behind the surface only, identity
        cells, dist = cast.cells[keep], cast.distance_sigmas[keep]
        order = np.lexsort((dist, cells))  # by cell, then most occupied-ward last
        cells, dist = cells[order], dist[order]
        unique, starts = np.unique(cells, return_index=True)
        groups = np.append(starts, cells.size)
        state[unique] = merge_n(engine, state[unique], engine.fuzzify(dist), groups)
    return engine.defuzzify(state).reshape(spec.shape)
