"""The runtime, applied at the edges of the core (`simulate`'s public wrapper, the fit's
programs, a sweep's chunks, the CLI): the program store, the compilation cache, XLA's CPU
flags, lazy imports, atomic file writes, and the uses of JAX's private API. `model/` and
`solve/` import nothing from here (tests/test_layout.py)."""
