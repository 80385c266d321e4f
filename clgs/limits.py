"""Bounds on the counts a user may ask for, shared by the settings' checks everywhere (the command
line, the methods' options, the settings dataclasses): beyond them a number is a typo (``1e23``),
not a plan, and is refused with the range instead of running for ever. Imports nothing."""

# training or SART iterations: R2-Gaussian's 30 000 takes hours on a CPU; ten million, years
MAX_ITERATIONS = 10_000_000
