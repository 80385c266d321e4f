"""The FDK/FBP ramp filter windows by name: one list, read by the filter (:mod:`clgs.ct.fdk`) and by
the method's ``--filter`` choice (:mod:`clgs.methods.builtin`), which must not import numpy to list."""
from __future__ import annotations

FILTERS = ("ram-lak", "shepp-logan", "cosine", "hamming", "hann")
