"""Measuring mi_amr: benchmarks, the peers beside it, the stability suite, the reference
images. Nothing else in the package imports this."""
