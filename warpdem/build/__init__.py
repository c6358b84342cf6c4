"""Everything that turns a scene into a Model before the first step: meshing and geology, packing, the builder and
its initial state (DESIGN.md, "What a user does").  Imports the stages below it, never the run above it.

Called as a function, ``warpdem.build(scene, device=...)`` is :func:`warpdem.api.build` (the package answers the call
so that the API's name and the folder's can be the same; see warpdem/__init__.py)."""
