"""Figures (matplotlib, imported lazily; never imported by the numerical core)."""
