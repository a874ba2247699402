"""The paper's probabilistic systems, kept as baselines: Elfes' exact 1-D grid and the closed-form OPDF.

- :func:`elfes_1d`: Bayes over every configuration of a 1-D grid (eqs. 1-2), the
  ground truth the closed form approximates; exponential in the number of cells.
- :func:`opdf`: the closed-form inverse sensor model (eq. 4, in DESIGN.md's reading).
- :func:`merge`: eq. 3; :func:`update_logodds` is the same merge as a sum in
  log-odds, clamped as OctoMap does so that a cell can still change its mind.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "BAYES_OCCUPIED_EXTENT",
    "CLAMP_MAX",
    "CLAMP_MIN",
    "ELFES_MAX_CELLS",
    "elfes_1d",
    "logodds",
    "merge",
    "opdf",
    "probability",
    "update_logodds",
]

#: Refuse exact Bayes beyond this many cells (2**20 configurations, ~20 MB of bits).
ELFES_MAX_CELLS = 20


def opdf(distance: np.ndarray | float, sigma: np.ndarray | float) -> np.ndarray:
    """Closed-form occupancy probability of a cell at ``distance`` from the measured surface (eq. 4).

    ``P(d) = 7/20 + 3/20 / (1 + exp(-2 (d + 2 sigma) / sigma)) + 3/20 exp(-d^2 / sigma^2)``:
    0.35 well in front of the surface, a peak of about 0.65 on it, 0.5 behind.
    The seed's eq. 4 is garbled by text extraction; this is DESIGN.md's reading,
    which gives the shape the paper's figure 2 describes.

    Parameters
    ----------
    distance : float or array
        ``cell position - measured range`` (eq. 5), any unit.
    sigma : float or array, > 0
        Standard deviation of the range, same unit (broadcast with ``distance``).

    Returns
    -------
    float64 array of the broadcast shape, in [0.35, 0.65].
    """
    d = np.asarray(distance, dtype=np.float64)
    s = np.asarray(sigma, dtype=np.float64)
    if np.any(~(s > 0.0)) or np.any(~np.isfinite(s)):
        raise ValueError(f"sigma must be finite and > 0, got {sigma!r}")
    t = d / s
    # 1 / (1 + exp(-x)) written with tanh so that large |t| neither overflows nor warns
    rising = 0.5 * (1.0 + np.tanh(t + 2.0))
    return 7.0 / 20.0 + 3.0 / 20.0 * rising + 3.0 / 20.0 * np.exp(-t * t)


def _occupied_extent(tolerance: float = 1e-3) -> float:
    # Last place (in sigmas, to 0.01) where the OPDF is still farther than `tolerance` from 0.5.
    t = np.arange(0.0, 20.0, 1e-4)
    far = np.flatnonzero(np.abs(opdf(t, 1.0) - 0.5) > tolerance)
    return math.ceil(t[far[-1]] * 100.0) / 100.0


#: Sigmas behind the surface past which :func:`opdf` is 0.5 to within 1e-3: a beam updates no further.
BAYES_OCCUPIED_EXTENT: float = _occupied_extent()


def logodds(p: np.ndarray | float) -> np.ndarray:
    """``log(p / (1 - p))``; p in [0, 1] (0 and 1 give -inf and +inf)."""
    p = np.asarray(p, dtype=np.float64)
    if np.any(~((p >= 0.0) & (p <= 1.0))):
        raise ValueError(f"p must be probabilities in [0, 1], got {p!r}")
    with np.errstate(divide="ignore"):
        return np.log(p) - np.log1p(-p)


def probability(l: np.ndarray | float) -> np.ndarray:
    """Inverse of :func:`logodds`: ``1 / (1 + exp(-l))``, stable for any l (NaN stays NaN)."""
    l = np.asarray(l, dtype=np.float64)
    return 0.5 * (1.0 + np.tanh(0.5 * l))


#: Log-odds bounds of a cell, OctoMap's defaults (``clamping_thres_min = 0.1192``, ``_max = 0.971``).
CLAMP_MIN: float = float(logodds(0.1192))
CLAMP_MAX: float = float(logodds(0.971))


def merge(p1: np.ndarray | float, p2: np.ndarray | float) -> np.ndarray:
    """Bayes merge of two occupancy probabilities of the same cell (eq. 3).

    ``P = p1 p2 / (p1 p2 + (1 - p1)(1 - p2))``; 0.5 is neutral. Equivalent to
    adding log-odds.

    Raises
    ------
    ValueError
        A probability outside [0, 1], or a certain 0 merged with a certain 1 (undefined).
    """
    a = np.asarray(p1, dtype=np.float64)
    b = np.asarray(p2, dtype=np.float64)
    for name, v in (("p1", a), ("p2", b)):
        if np.any(~((v >= 0.0) & (v <= 1.0))):
            raise ValueError(f"{name} must be probabilities in [0, 1], got {v!r}")
    num = a * b
    den = num + (1.0 - a) * (1.0 - b)
    if np.any(den == 0.0):
        raise ValueError("merge of a certain 0 with a certain 1 is undefined (p1 and p2 contradict with certainty)")
    return num / den


def update_logodds(current: np.ndarray, evidence: np.ndarray) -> np.ndarray:
    """Eq. 3 in log-odds, clamped: ``clip(current + evidence, CLAMP_MIN, CLAMP_MAX)``.

    Clamping (OctoMap's ``updateNodeLogOdds``) bounds how sure a cell can get,
    so that a changed world is relearned in a few scans. ``current`` and
    ``evidence`` broadcast; the result has ``current``'s float dtype.
    """
    current = np.asarray(current)
    dtype = current.dtype if np.issubdtype(current.dtype, np.floating) else np.float64
    return np.clip(current + np.asarray(evidence), CLAMP_MIN, CLAMP_MAX).astype(dtype, copy=False)


def elfes_1d(
    n_cells: int, cell_size: float, measured_range: float, sigma: float, prior: float = 0.5
) -> np.ndarray:
    """Exact Bayesian occupancy of a 1-D grid given one range reading (eqs. 1-2, Elfes).

    Cell ``i`` spans ``[i, i + 1) * cell_size`` from the sensor at 0. Every
    configuration of the ``n_cells`` cells is weighed by its prior (each cell
    occupied with probability ``prior``, independently) times the likelihood of
    the reading: the first occupied cell along the beam returns it, with
    Gaussian noise ``sigma`` about its centre. If no cell is occupied, the beam
    is taken to return from a wall one cell beyond the grid (centre of cell
    ``n_cells``), so an empty line explains a reading at the far end.

    Parameters
    ----------
    n_cells : int
        1 .. :data:`ELFES_MAX_CELLS` (the cost is ``2**n_cells`` configurations).
    cell_size, sigma : float
        Positive, same length unit as ``measured_range``.
    measured_range : float
        The reading, finite.
    prior : float
        Prior occupancy of each cell, in (0, 1).

    Returns
    -------
    (n_cells,) float64 array
        ``P(cell i occupied | reading)``.

    Raises
    ------
    ValueError
        Naming the offending argument; in particular ``n_cells`` above the limit.
    """
    if isinstance(n_cells, bool) or not isinstance(n_cells, (int, np.integer)) or n_cells < 1:
        raise ValueError(f"n_cells must be a positive integer, got {n_cells!r}")
    if n_cells > ELFES_MAX_CELLS:
        raise ValueError(
            f"n_cells={n_cells} is above the limit of {ELFES_MAX_CELLS}: exact Bayes enumerates "
            f"2**n_cells configurations ({2**n_cells:,}); use opdf for larger grids"
        )
    for name, value in (("cell_size", cell_size), ("sigma", sigma)):
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    if not math.isfinite(measured_range):
        raise ValueError(f"measured_range must be finite, got {measured_range!r}")
    if not 0.0 < prior < 1.0:
        raise ValueError(f"prior must be in (0, 1), got {prior!r}")

    n = int(n_cells)
    # Row c of `bits` is configuration c: bit i says whether cell i is occupied.
    bits = ((np.arange(2**n, dtype=np.int64)[:, None] >> np.arange(n)) & 1).astype(np.uint8)
    occupied = bits.sum(axis=1)
    first = np.where(occupied > 0, np.argmax(bits, axis=1), n)
    centres = (np.arange(n + 1) + 0.5) * cell_size
    # Log weights: the Gaussian's constant factor cancels in the normalisation.
    log_like = -0.5 * ((measured_range - centres[first]) / sigma) ** 2
    log_prior = occupied * math.log(prior) + (n - occupied) * math.log1p(-prior)
    log_w = log_like + log_prior
    w = np.exp(log_w - log_w.max())
    return (w @ bits) / w.sum()
