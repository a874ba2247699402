"""The last scan as the web page draws it: its beam ends in the map frame, thinned."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.scans.scan import Scan
from fuzzyocc import LaserScan
from fuzzyocc.maps import scan_parts

#: The scans/last view draws at most this many beams.
MAX_VIEW_BEAMS = 4096


@dataclass(frozen=True)
class ScanView:
    origin: list[float]
    endpoints: list[list[float]]
    hit: list[bool]


def scan_view(scan: Scan) -> ScanView:
    """Beam ends of a scan in the map frame, evenly thinned to at most ``MAX_VIEW_BEAMS`` of its rays.

    Made part by part (``fuzzyocc.maps.scan_parts``): the rays of a whole scan of millions of beams
    take about 150 bytes a beam.
    """
    n = scan.beam_count
    rays_in_all = scan.usable(slice(0, n)) if isinstance(scan, LaserScan) else n
    step = max(1, math.ceil(rays_in_all / MAX_VIEW_BEAMS))
    ends, hit, seen = [], [], 0
    for part in scan_parts(scan):
        rays = scan.to_rays(beams=part)
        start = -seen % step  # this part's first ray to show: every step-th of the scan's rays
        ends.append(rays.endpoints[start::step])
        hit.append(rays.hit[start::step])
        seen += rays.ranges.size
    return ScanView(
        origin=[float(v) for v in rays.origin],
        endpoints=np.round(np.concatenate(ends), 4).tolist(),
        hit=np.concatenate(hit).tolist(),
    )
