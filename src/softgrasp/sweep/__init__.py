"""Sweeps: many plans over a grid or random sample of options, run on Dask (:mod:`.engine`)."""
