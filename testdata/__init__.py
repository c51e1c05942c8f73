"""Test subjects made by code, for the tests and benchmarks (not part of the installed library):
:mod:`.procedural` a small textured person-like mesh, :mod:`.synthetic` Anny subjects with known
body parameters."""
