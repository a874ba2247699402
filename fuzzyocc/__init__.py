"""Fuzzy occupancy mapping core (Payeur's fuzzy fusion, Bayesian baselines, grids, ray casting)."""
