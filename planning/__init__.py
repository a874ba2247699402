"""Risk-aware path planning with OMPL on a risk grid."""
