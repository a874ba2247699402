"""Fuzzy occupancy mapping core (Payeur's fuzzy fusion, Bayesian baselines, grids, ray casting)."""

from fuzzyocc.config import GridSpec, LatticeSpec, SensorModel
from fuzzyocc.engine import FuzzyEngine
from fuzzyocc.maps import BayesMap, FuzzyMap, IntegrationStats, allocation_bound, cast_work
from fuzzyocc.scans import LaserScan, PointCloud

__all__ = [
    "BayesMap",
    "FuzzyEngine",
    "FuzzyMap",
    "GridSpec",
    "IntegrationStats",
    "LatticeSpec",
    "LaserScan",
    "PointCloud",
    "SensorModel",
    "allocation_bound",
    "cast_work",
]
