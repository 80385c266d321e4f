"""How many modes a shape model keeps, decided from its population's figures.

The rule (:func:`choose_modes`): the fewest modes that either hold ``variance`` of the
population's variance (compactness) or after which one more mode improves the leave-one-out
generalisation by less than ``tolerance_mm`` (the next mode reaches new subjects no better than
that: it describes the training subjects, not the population). Fewer modes keep a stronger
prior, which is what a fit to a few views needs; ``n_modes`` overrides the rule, ``variance``
alone (``tolerance_mm`` None or 0) is the classic rule.
"""
from __future__ import annotations

from clgs.errors import InputError

#: defaults of the rule: 95 % of the variance, or a next mode that gains under 0.05 mm
VARIANCE = 0.95
TOLERANCE_MM = 0.05


def choose_modes(figures: dict | None, n_available: int, variance: float | None = VARIANCE,
                 tolerance_mm: float | None = TOLERANCE_MM, n_modes: int | None = None) -> dict:
    """{"n_modes", "reason", "rule"} for a population whose PCA has ``n_available`` modes and
    whose :func:`clgs.shape.statistics.field_space_figures` are ``figures`` (None when there were
    too few subjects for them: the variance rule alone). ``compactness`` must cover every mode for
    the variance rule (the caller passes the full spectrum's cumulative share)."""
    rule = {"variance": variance, "generalisation_tolerance_mm": tolerance_mm, "n_modes": n_modes}
    if n_available <= 0:
        return {"n_modes": 0, "reason": "the subjects do not vary: no modes", "rule": rule}
    if n_modes is not None:
        if int(n_modes) < 1:
            raise InputError(f"n_modes must be >= 1, got {n_modes}")
        m = min(int(n_modes), n_available)
        reason = (f"{m} modes as asked (--n-modes)" if m == int(n_modes) else
                  f"{m} modes: {n_modes} were asked (--n-modes), the population's PCA has {n_available}")
        return {"n_modes": m, "reason": reason, "rule": rule}
    if variance is None or not (0 < float(variance) <= 1):
        raise InputError(f"variance must be in (0, 1], got {variance}")
    if tolerance_mm is not None and (tolerance_mm < 0 or tolerance_mm != tolerance_mm):
        raise InputError(f"the generalisation tolerance must be >= 0 mm, got {tolerance_mm}")
    compact = list((figures or {}).get("compactness_all") or (figures or {}).get("compactness") or [])
    by_variance = next((i + 1 for i, c in enumerate(compact) if c >= float(variance) - 1e-12), n_available)
    m, reason = min(by_variance, n_available), f"the first {min(by_variance, n_available)} hold " \
                                                f"{100 * float(variance):.0f} % of the variance"
    general = list((figures or {}).get("generalisation_mm") or [])
    if tolerance_mm and len(general) >= 2:
        for i in range(len(general) - 1):
            if general[i] - general[i + 1] < float(tolerance_mm):
                if i + 1 < m:
                    m = i + 1
                    reason = (f"a mode beyond {m} improves leave-one-out generalisation by "
                              f"{general[i] - general[i + 1]:.3f} mm (< {float(tolerance_mm):g} mm)")
                break
    return {"n_modes": int(m), "reason": reason, "rule": rule}
