"""Plain torch references of the kernels, for tests and benchmarks."""
