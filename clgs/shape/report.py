"""What a built model says about itself, as lines of text: its figures (compactness,
generalisation, specificity per mode count), how many modes it kept and why, and which subjects
were mirrored. Read from the model file's metadata record, so ``build-model`` and ``info`` print
the same thing without recomputing it."""
from __future__ import annotations


def figure_lines(figures: dict, what: str) -> list:
    """Lines for :func:`clgs.shape.statistics.field_space_figures`' ``figures``; ``what`` names the
    PCA they describe."""
    def row(values, fmt):
        return " / ".join(fmt.format(v) for v in values)

    return [f"{what}, modes {row(figures['modes'], '{}')}:",
            f"  compactness {row([100 * c for c in figures['compactness']], '{:.1f}')} % of the variance",
            f"  generalisation {row(figures['generalisation_mm'], '{:.2f}')} mm (leave-one-out, mean distance)",
            f"  specificity {row(figures['specificity_mm'], '{:.2f}')} mm (random shapes to the nearest subject)"]


def model_lines(meta: dict) -> list:
    """The figures, the mode decision and the mirroring recorded in a model file's metadata
    (:func:`clgs.shape.model.read_metadata`); empty for a model built before they were recorded."""
    lines = []
    figures = meta.get("statistics")
    if figures:
        lines += figure_lines(figures, f"velocity PCA at {figures.get('measured_at', '?')}")
    choice = meta.get("mode_choice")
    if choice:
        lines.append(f"modes kept: {choice['n_modes']} ({choice['reason']}; "
                     f"variance kept {100 * float(meta.get('variance_kept', float('nan'))):.1f} %)")
    mirroring = meta.get("mirroring")
    if mirroring:
        subjects = mirroring.get("subjects") or {}
        mirrored = [sid for sid, r in subjects.items() if r.get("mirrored")]
        sides = {}
        for r in subjects.values():
            sides[r.get("side")] = sides.get(r.get("side"), 0) + 1
        counts = ", ".join(f"{n} {side}" for side, n in sorted(sides.items(), key=lambda kv: str(kv[0])))
        lines.append(f"sides: {counts}; template side {mirroring.get('template_side')}; "
                     + (f"mirrored into it: {', '.join(mirrored)}" if mirrored else "none mirrored"))
    return lines
