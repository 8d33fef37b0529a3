"""`millsense replay --plot OUT.png`: one figure of a replay, drawn after the JSON lines.

Four panels over the replay time `t` (s after the capture's first sample):
spindle speed, cutting torque (with its eq. 20 uncertainty band), forces, and
depths of cut. Alarms are vertical lines (colour by level) across every panel;
revolutions that span lost samples or a discontinuity (`valid: false`, or
`lost_samples` > 0) are shaded, so a gap in a line reads as "no data", not
"zero".

matplotlib is an optional extra (`pip install 'millsense[plot]'`). This module
is imported only when `--plot` is given, and it imports matplotlib itself only
in `require_matplotlib()`, so a missing extra is one clear error line instead
of a traceback. The Agg backend is chosen explicitly: an edge box has no
display, and the figure is only ever written to a file.
"""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path
from typing import Any

INSTALL_HINT = "--plot needs matplotlib, which is not installed: pip install 'millsense[plot]'"

# Alarm level -> line colour and style (breakage and crash stand out from overloads).
ALARM_STYLE = {
    "warning": ("#e69f00", "--"),
    "overload": ("#d55e00", "-"),
    "crash": ("#000000", "-"),
    "tool_breakage": ("#cc00cc", "-"),
    "daq_lost": ("#7f7f7f", ":"),
    "clear": ("#009e73", ":"),
}
LOST_SHADE = "#bbbbbb"
DPI = 100
SIZE_IN = (10.0, 8.5)


class PlotUnavailable(RuntimeError):
    """matplotlib (the `plot` extra) is missing."""


def require_matplotlib() -> None:
    """Fail fast, before any output, when the plot extra is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        from matplotlib.figure import Figure  # noqa: F401 - the class the plot is drawn with
    except ImportError:
        raise PlotUnavailable(INSTALL_HINT) from None


def _series(rows: list[dict], key: str) -> list[float]:
    """A payload field as floats, None -> NaN (a gap in the line)."""
    out = []
    for r in rows:
        v = r.get(key)
        out.append(float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan)
    return out


class ReplayPlot:
    """Collects replay payloads (estimates and alarms) and writes the figure."""

    def __init__(self) -> None:
        self.estimates: list[dict[str, Any]] = []
        self.alarms: list[dict[str, Any]] = []

    def add(self, payload: dict[str, Any]) -> None:
        if payload.get("t") is None:
            return
        if payload.get("type") == "alarm":
            self.alarms.append(payload)
        elif payload.get("type") == "estimate":
            self.estimates.append(payload)

    def lost_spans(self) -> list[tuple[float, float]]:
        """(start, end) in s of every revolution built on missing samples."""
        spans: list[tuple[float, float]] = []
        prev_t = None
        for e in self.estimates:
            t = float(e["t"])
            if e.get("valid") is False or (e.get("lost_samples") or 0) > 0:
                start = prev_t if prev_t is not None else t
                if spans and abs(spans[-1][1] - start) < 1e-9:
                    spans[-1] = (spans[-1][0], t)       # merge neighbours into one shaded span
                else:
                    spans.append((start, t))
            prev_t = t
        return spans

    def write(self, path: str | Path, title: str) -> None:
        self.figure(title).savefig(path, dpi=DPI, format="png")

    def figure(self, title: str) -> Any:
        """The figure `write` saves (a matplotlib Figure), for a test to read its axes."""
        require_matplotlib()
        from matplotlib.figure import Figure

        fig = Figure(figsize=SIZE_IN, dpi=DPI, layout="constrained")
        axes = fig.subplots(4, 1, sharex=True)
        t = _series(self.estimates, "t")
        self._panel(axes[0], t, [("spindle_rpm", "spindle", "C0")], "spindle (rpm)")
        self._torque(axes[1], t)
        self._panel(axes[2], t, [("force_n", "resultant |F| (eq. 18)", "C3"),
                                 ("force_tangential_n", "tangential T/R", "C1"),
                                 ("force_feed_n", "feed drive", "C2")], "force (N)")
        self._panel(axes[3], t, [("radial_depth_mm", "radial d_r", "C4"),
                                 ("axial_depth_mm", "axial d_a", "C5")], "depth of cut (mm)")
        self._depth_note(axes[3])
        for ax in axes:
            for a, b in self.lost_spans():
                ax.axvspan(a, b, color=LOST_SHADE, alpha=0.6, lw=0)
            for al in self.alarms:
                color, style = ALARM_STYLE.get(al.get("level"), ("#7f7f7f", "-."))
                ax.axvline(float(al["t"]), color=color, ls=style, lw=1.2)
            ax.grid(True, alpha=0.3)
            # Values in their unit: a spindle steady at 600 rpm spans a fraction of an rpm, and matplotlib's
            # default labelled that axis `+5.999e2` with ticks of 0.01 (issue 39). Plain numbers, no offset.
            ax.ticklabel_format(axis="y", style="plain", useOffset=False)
        self._legend_extras(axes[0])
        axes[-1].set_xlabel("time after the capture's first sample (s)")
        n_alarms = Counter(a.get("level") for a in self.alarms)
        alarm_text = ", ".join(f"{k} {v}" for k, v in sorted(n_alarms.items())) or "none"
        fig.suptitle(f"{title}\n{len(self.estimates)} revolutions; alarms: {alarm_text}", fontsize=11)
        return fig

    def _panel(self, ax, t, fields, ylabel: str) -> None:
        drawn = False
        for key, label, color in fields:
            y = _series(self.estimates, key)
            if any(not math.isnan(v) for v in y):
                ax.plot(t, y, color=color, lw=1.2, label=label)
                drawn = True
        ax.set_ylabel(ylabel)
        if drawn and len(fields) > 1:
            ax.legend(loc="upper left", fontsize=8, framealpha=0.8)

    def _torque(self, ax, t) -> None:
        y = _series(self.estimates, "torque_nm")
        s = _series(self.estimates, "torque_sigma_nm")
        ax.plot(t, y, color="C0", lw=1.2, label="cutting torque (eq. 13)")
        lo = [a - 2 * b for a, b in zip(y, s)]
        hi = [a + 2 * b for a, b in zip(y, s)]
        ax.fill_between(t, lo, hi, color="C0", alpha=0.25, lw=0, label="±2σ (eq. 20)")
        ax.set_ylabel("torque (N·m)")
        ax.legend(loc="upper left", fontsize=8, framealpha=0.8)

    def _depth_note(self, ax) -> None:
        """Say why the depth panel is empty instead of leaving a blank box."""
        if any(not math.isnan(v) for k in ("radial_depth_mm", "axial_depth_mm") for v in _series(self.estimates, k)):
            return
        statuses = Counter(e.get("depth_status") for e in self.estimates if e.get("depth_status"))
        text = ", ".join(f"{k} ×{v}" for k, v in statuses.most_common()) or "depth estimation off"
        ax.text(0.5, 0.5, f"no depth estimates ({text})", transform=ax.transAxes, ha="center", va="center",
                fontsize=9, color="#555555")

    def _legend_extras(self, ax) -> None:
        """One legend entry per alarm level present and for the lost-sample shading."""
        from matplotlib.lines import Line2D
        from matplotlib.patches import Patch

        handles = []
        for level in dict.fromkeys(a.get("level") for a in self.alarms):
            color, style = ALARM_STYLE.get(level, ("#7f7f7f", "-."))
            handles.append(Line2D([], [], color=color, ls=style, lw=1.2, label=f"alarm: {level}"))
        if self.lost_spans():
            handles.append(Patch(color=LOST_SHADE, alpha=0.6, label="lost samples"))
        if handles:
            ax.legend(handles=handles, loc="upper right", fontsize=8, framealpha=0.8)
