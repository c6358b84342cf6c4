"""Outputs and inputs of a run: the USD stage, VTU frames, the time series, HDF5 checkpoints and restarts, plots and
preview pictures (DESIGN.md, "Output").  Reads the simulation below it; the runner and the CLI drive it."""
