"""`layerbvh sweep`: the grid of scenes x configurations on Dask, one process per point, the merged table, SLURM
workers."""
