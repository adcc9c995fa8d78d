"""Numerical experiments on point-level synthetic scenes (the papers' §4.1) and their generators."""
