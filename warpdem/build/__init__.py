"""Everything that turns a scene into a Model before the first step: meshing and geology, packing, the builder and
its initial state (DESIGN.md, "What a user does").  Imports the stages below it, never the run above it."""
