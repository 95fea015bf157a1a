"""Experiment grids and the paper-style report (appendix D-F)."""
