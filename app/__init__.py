"""HTTP service: named fuzzy occupancy maps, scan fusion and risk-aware plans."""
