"""Error against run time: the training log, its CSV and plot, a live progress bar, a summary.

Each row is one evaluation: ``iteration``, ``seconds`` (training time: the optimisation alone,
without evaluations and file writes, so curves of different runs compare), ``wall`` (since the
run began, everything included), ``n_gaussians``, the loss terms averaged since the previous row,
and whatever the evaluation measured (projection PSNR; 3D PSNR / SSIM when the truth is known).
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from clgs.io import atomic

# the figures the progress bar and the summary show, in order, when present
HEADLINE = ("loss", "n_gaussians", "proj_psnr", "psnr3d", "ssim3d")
RATE = "it/s"  # iterations per second of training time (evaluations and file writes left out)


class TrainingLog:
    def __init__(self, rows=None):
        self.rows: list = list(rows or [])

    def add(self, row: dict) -> None:
        self.rows.append(dict(row))

    @property
    def columns(self) -> list:
        cols: list = []
        for r in self.rows:
            cols += [k for k in r if k not in cols]
        return cols

    def last(self, key, default=None):
        for r in reversed(self.rows):
            if r.get(key) is not None:
                return r[key]
        return default

    # ------------------------------------------------------------------ files
    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=self.columns, lineterminator="\n")
        w.writeheader()
        for r in self.rows:
            w.writerow({k: ("" if v is None else (f"{v:.7g}" if isinstance(v, float) else v)) for k, v in r.items()})
        return buf.getvalue()

    def write_csv(self, path) -> Path:
        return atomic.write_text(path, self.to_csv())

    @staticmethod
    def read_csv(path) -> TrainingLog:
        rows = []
        with open(path, newline="") as fh:
            for r in csv.DictReader(fh):
                rows.append({k: _number(v) for k, v in r.items()})
        return TrainingLog(rows)

    def plot(self, path, title: str = "error against run time") -> Path:
        """PNG: loss (log scale), projection PSNR and, when known, 3D PSNR / SSIM against seconds."""
        import matplotlib

        matplotlib.use("Agg", force=False)
        from matplotlib.figure import Figure

        panels = [("loss", "loss (log)", True), ("proj_psnr", "projection PSNR (dB)", False)]
        if any(r.get("psnr3d") is not None for r in self.rows):
            panels += [("psnr3d", "3D PSNR (dB)", False), ("ssim3d", "3D SSIM", False)]
        fig = Figure(figsize=(4.0 * len(panels), 3.4), dpi=100)
        for i, (key, label, log) in enumerate(panels):
            ax = fig.add_subplot(1, len(panels), i + 1)
            pts = [(r["seconds"], r[key]) for r in self.rows
                   if r.get(key) is not None and r.get("seconds") is not None and math.isfinite(float(r[key]))]
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=".", lw=1)
            if log and pts and min(p[1] for p in pts) > 0:
                ax.set_yscale("log")
            ax.set_xlabel("training time (s)")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        fig.suptitle(title)
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        return atomic.write_bytes(path, buf.getvalue())

    # ------------------------------------------------------------------ text
    def summary(self) -> str:
        """A small table: first and last evaluation, and the best of each figure."""
        if not self.rows:
            return "(no evaluations logged)"
        first, last = self.rows[0], self.rows[-1]
        keys = [k for k in ("iteration", "seconds", *HEADLINE) if k in self.columns]
        best = {}
        for k in ("proj_psnr", "psnr3d", "ssim3d"):
            vals = [r[k] for r in self.rows if r.get(k) is not None]
            if vals:
                best[k] = max(vals)
        its = last.get("iteration", 0) - first.get("iteration", 0)
        secs = (last.get("seconds") or 0) - (first.get("seconds") or 0)
        rate = self.rate()
        lines = [f"{'':12s}" + "".join(f"{k:>13s}" for k in keys)]
        for label, r in (("first", first), ("last", last)):
            lines.append(f"{label:12s}" + "".join(f"{_fmt(r.get(k)):>13s}" for k in keys))
        if best:
            lines.append(f"{'best':12s}" + "".join(f"{_fmt(best.get(k)) if k in best else '':>13s}" for k in keys))
        if rate is not None:
            lines.append(f"{its} iterations in {secs:.1f} s of training: {fmt_rate(rate)} {RATE}")
        reached = self.time_to_quality()
        if reached:
            lines.append("first reached (3D PSNR, at training s / wall s since the start; linear between the two "
                         "evaluations logged around each level): "
                         + ", ".join(f"{level:g} dB at {t:.1f} / {w:.1f} s" for level, t, w in reached))
        return "\n".join(lines)

    def rate(self, iteration=None, seconds=None):
        """Iterations per second of training time from the first row to (``iteration``, ``seconds``)
        (default: the last row); None before there is any. What the summary and the bar show."""
        if not self.rows:
            return None
        first, last = self.rows[0], self.rows[-1]
        iteration = last.get("iteration", 0) if iteration is None else iteration
        seconds = (last.get("seconds") or 0) if seconds is None else seconds
        its = iteration - first.get("iteration", 0)
        secs = seconds - (first.get("seconds") or 0)
        return its / secs if secs > 0 and its > 0 else None

    def headline(self) -> dict:
        """The last row's figures the summary's ``last`` line shows (HEADLINE) and its it/s: what
        the progress bar shows at the end."""
        if not self.rows:
            return {}
        last = self.rows[-1]
        out = {k: last[k] for k in HEADLINE if last.get(k) is not None}
        rate = self.rate()
        if rate is not None:
            out[RATE] = rate
        return out

    def time_to_quality(self, key: str = "psnr3d", step: float = 1.0) -> list:
        """[(level, training seconds, wall seconds)]: when ``key`` first reached each whole multiple
        of ``step`` from the first logged value up to the best. The curve is known only at the
        logged evaluations: the time is interpolated linearly between the last row below the level
        and the first row at or above it (so two levels passed between the same two rows get
        different times, in proportion to the values logged there). The trainer logs densely early
        on (``log_early``), where the curve rises fastest."""
        pts = [(float(r[key]), r.get("seconds"), r.get("wall")) for r in self.rows
               if r.get(key) is not None and r.get("seconds") is not None and math.isfinite(float(r[key]))]
        if len(pts) < 2:
            return []
        lo = math.floor(pts[0][0] / step) * step + step
        hi = max(p[0] for p in pts)
        out = []
        level = lo
        while level <= hi + 1e-12:
            i = next(i for i, p in enumerate(pts) if p[0] >= level)  # i >= 1: the first value is below lo
            (v0, t0, w0), (v1, t1, w1) = pts[i - 1], pts[i]
            w0 = t0 if w0 is None else w0
            w1 = t1 if w1 is None else w1
            f = (level - v0) / (v1 - v0)
            out.append((round(level, 6), float(t0 + f * (t1 - t0)), float(w0 + f * (w1 - w0))))
            level += step
        return out


class Progress:
    """Progress over iterations with ETA and the figures of the training log (a live bar on a
    terminal, a line every few seconds in a log); silent when ``enabled`` is False or progress is
    off (:func:`clgs.progress.progress_enabled`).

    The bar shows the log's figures under the log's names: those of the last evaluation row
    (:data:`HEADLINE`, as the summary's ``last`` line) and ``it/s``, iterations per second of
    training time as the summary computes it, not tqdm's wall-clock rate (which counts the
    evaluations too). At the end (:meth:`finish`) it shows the summary's own figures; each set of
    figures also goes to :func:`clgs.progress.listen`'s listeners."""

    def __init__(self, total: int, initial: int = 0, enabled: bool = True, desc: str = "train"):
        from clgs.progress import progress_bar, progress_enabled

        self.bar = None
        self.desc = desc
        self.figures: dict = {}
        if enabled and progress_enabled():
            self.bar = progress_bar(total=total, initial=initial, desc=desc, unit="it", dynamic_ncols=True,
                                    leave=True, rate=False)

    def update(self, n: int = 1, figures: dict | None = None) -> None:
        """``n`` more iterations; ``figures`` (optional) replace those shown (None values are dropped)."""
        if figures:
            self.set_figures(figures, emit=False)
        if self.bar is not None:
            self.bar.update(n)

    def set_figures(self, figures: dict, final: bool = False, emit: bool = True) -> None:
        """Show ``figures`` (name -> value; HEADLINE and it/s, in that order); listeners get them
        with ``final`` when ``emit``."""
        from clgs import progress

        self.figures = {k: figures[k] for k in (*HEADLINE, RATE) if figures.get(k) is not None}
        if emit:
            progress.emit({"event": "figures", "desc": self.desc, "figures": dict(self.figures), "final": final})
        if self.bar is not None:
            self.bar.set_postfix({k: (fmt_rate(v) if k == RATE else _fmt(v)) for k, v in self.figures.items()},
                                 refresh=False)

    def finish(self, figures: dict) -> None:
        """The final figures (the summary's), shown on the bar's last line, then close."""
        self.set_figures(figures, final=True)
        self.close()

    def write(self, text: str) -> None:
        if self.bar is not None:
            self.bar.write(text)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def fmt_rate(rate) -> str:
    """it/s as the summary and the bar print it."""
    return f"{float(rate):.1f}"


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, int):
        return str(v)
    v = float(v)
    if v == 0 or 1e-3 <= abs(v) < 1e5:
        return f"{v:.4g}"
    return f"{v:.3e}"


def _number(text: str):
    if text == "":
        return None
    try:
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError:
            return text
