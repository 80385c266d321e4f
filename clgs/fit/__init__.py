"""Fitting Gaussians to X-ray projections, whatever the method: the Gaussian set, losses,
densification, the trainer and its schedules, log and checkpoints, the settings every Gaussian
method shares, evaluation during training and the run's output files.

May import: :mod:`clgs.ops`, :mod:`clgs.reference`, :mod:`clgs.ct`, :mod:`clgs.metrics`,
:mod:`clgs.io` and the modules below them. Not methods, anatomies, shapes or the CLI.
"""
