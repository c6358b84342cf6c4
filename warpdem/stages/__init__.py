"""The host side of each physics stage, one module per stage, mirroring :mod:`warpdem.kernels` (DESIGN.md, "Physics,
stage by stage"): each wraps its kernels' launches and owns its stage's buffers.  Imports the Model and the kernels
below it, never the builder, the run or the outputs above it."""
