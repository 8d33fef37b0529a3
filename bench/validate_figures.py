"""Figures of `bench/validate.py`, in the papers' style: estimate and truth over time, alarms marked.

Drawn with matplotlib's object API on the Agg backend (no display, no pyplot
global state); every PNG at 100 dpi so each stays around 100 KB.
"""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402

DPI = 100
TRUTH = {"color": "black", "lw": 1.6}
HEADROOM = 1.55                  # y range over the largest true value: room for the legends above the data
MAX_TOP = 2.5                    # ... but an estimate far off at entry is clipped rather than squash the plot
TRANSITION_SHADE = {"color": "#f2e6b3", "alpha": 0.6, "lw": 0}
ALARM_COLOR = {"tool_breakage": "#cc00cc", "overload": "#d55e00", "warning": "#e69f00", "crash": "black",
               "clear": "#009e73"}


def _spans(truth: list[dict], seg: dict[int, str], wanted: str) -> list[tuple[float, float]]:
    """Merged time spans of the truth revolutions in segment `wanted`."""
    spans: list[tuple[float, float]] = []
    for t in truth:
        if seg.get(t["rev"]) != wanted:
            continue
        start = t["t_end_s"] - 60.0 / max(t["spindle_rpm"], 1e-6)
        if spans and start - spans[-1][1] < 1e-3:
            spans[-1] = (spans[-1][0], t["t_end_s"])
        else:
            spans.append((start, t["t_end_s"]))
    return spans


def _series(res, key: str) -> tuple[list[float], list[float]]:
    t, y = [], []
    for e in res.estimates:
        t.append(e["t"])
        v = e.get(key)
        y.append(math.nan if v is None else float(v))
    return t, y


def _marks(axes, alarms, events, legend_ax) -> None:
    """Alarms of the run (solid) and the plant's own events (dashed), on every panel; one legend."""
    handles = {}
    for ax in axes:
        for a in alarms:
            h = ax.axvline(a["t"], color=ALARM_COLOR.get(a["level"], "grey"), lw=1.4)
            handles.setdefault(f"alarm: {a['level']} (t = {a['t']:.2f} s)", h)
        for ev in events:
            if ev["event"] == "tool_breakage":
                h = ax.axvline(ev["t_s"], color="black", ls="--", lw=1.0)
                handles.setdefault(f"flute breaks (truth, t = {ev['t_s']:.2f} s)", h)
    if handles:
        curves = legend_ax.get_legend()            # a second legend() would replace the curves' legend
        legend_ax.legend(list(handles.values()), list(handles), loc="upper right", fontsize=8, framealpha=0.9)
        if curves is not None:
            legend_ax.add_artist(curves)


def paper_figure(path, title: str, kind: str, truth, seg, main, extras, events, lead_mm: float = 0.0) -> None:
    """kind "P": force and d_a over time; kind "D": d_r and d_a over time.

    `main` is the paper's configuration; `extras` [(label, Result, style)] are drawn dashed beside it.
    Transitions (entry, exit, steps) are shaded: the steady-segment statistics leave them out.
    """
    fig = Figure(figsize=(9.5, 6.2), dpi=DPI, layout="constrained")
    axes = fig.subplots(2, 1, sharex=True)
    t_truth = [t["t_end_s"] for t in truth]
    if kind == "P":
        panels = [("force_n", "force_n", "resultant force |F| (N)", "estimate, C_f = 1.075"),
                  ("axial_depth_mm", "axial_depth_mm", "axial depth d_a (mm)", "estimate (torque, slot)")]
    else:
        panels = [("radial_depth_mm", "radial_depth_mm", "radial depth d_r (mm)", main.case.label),
                  ("axial_depth_mm", "axial_depth_mm", "axial depth d_a (mm)", main.case.label)]
    for ax, (e_key, t_key, ylabel, label) in zip(axes, panels):
        y_truth = [t[t_key] for t in truth]
        for a, b in _spans(truth, seg, "transition"):
            ax.axvspan(a, b, **TRANSITION_SHADE)
        if kind == "D":
            ax.fill_between(t_truth, [0.9 * v for v in y_truth], [1.1 * v for v in y_truth], color="#cccccc",
                            lw=0, label="truth ±10 % ([D] claim)")
        ax.plot(t_truth, y_truth, label="truth (simulator)", **TRUTH)
        if lead_mm and e_key == "axial_depth_mm":
            ax.plot(t_truth, [v + lead_mm if v > 0 else 0.0 for v in y_truth], color="#777777", ls=":", lw=1.4,
                    label=f"truth + taper lead πRk/4 = {lead_mm:.2f} mm")
        ax.plot(*_series(main, e_key), color="#d62728", lw=1.2, label=label)
        if kind == "D" or e_key == "force_n":          # [P]: the C_f variants differ in force only
            for extra_label, res, style in extras:
                ax.plot(*_series(res, e_key), label=extra_label, **style)
        ax.set_ylabel(ylabel)
        # headroom above the truth for the legends, so they never sit on the curves
        top = max(y_truth + [v + lead_mm for v in y_truth if e_key == "axial_depth_mm"])
        est_top = max((v for v in _series(main, e_key)[1] if not math.isnan(v)), default=0.0)
        ax.set_ylim(0, min(max(HEADROOM * top, 1.1 * est_top), MAX_TOP * top))
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper left", fontsize=8, framealpha=0.9)
    _marks(axes, main.alarms, events, axes[-1])
    axes[-1].set_xlabel("time (s); shaded: transitions (entry, exit, steps, feed changes)")
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=DPI)


def sigma_figure(path, rows) -> None:
    """Static sensitivity, [P] eq. 20: torque scatter against spindle speed, log-log, per gear.

    rows: dicts with rpm, gear, and per noise level: observed std and the estimator's mean sigma."""
    fig = Figure(figsize=(8.5, 6.4), dpi=DPI, layout="constrained")
    ax = fig.subplots()
    colors = {1.0: "#1f77b4", 5.0: "#d62728"}
    for noise, color in colors.items():
        for gear, marker in (("low-speed", "o"), ("high-speed", "s")):
            sel = [r for r in rows if r["gear"] == gear]
            rpm = [r["rpm"] for r in sel]
            ax.plot(rpm, [r[f"std_{noise:g}"] for r in sel], marker=marker, color=color, lw=1.2,
                    label=f"observed scatter, noise ×{noise:g}, {gear}")
            ax.plot(rpm, [r[f"sigma_{noise:g}"] for r in sel], marker=marker, color=color, lw=1.0, ls="--",
                    mfc="none", label=f"estimator's torque_sigma_nm, noise ×{noise:g}, {gear}")
            if len(sel) > 1:
                k = sel[0][f"std_{noise:g}"] * sel[0]["rpm"]
                ax.plot(rpm, [k / x for x in rpm], color="grey", lw=0.8, ls=":")
    ax.plot([], [], color="grey", lw=0.8, ls=":", label="∝ 1/ω through the first point (eq. 20)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks([300, 500, 700, 900, 1000, 1500, 2000, 2500])
    ax.set_xticklabels(["300", "500", "700", "900", "1000", "1500", "2000", "2500"])
    ax.minorticks_off()
    ax.axvline(950, color="grey", lw=0.6)
    ax.text(950, ax.get_ylim()[1], " gear change", va="top", fontsize=8, color="grey")
    ax.set_xlabel("spindle speed (rpm), log scale")
    ax.set_ylabel("torque error, 1σ over steady revolutions (N·m), log scale")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), framealpha=0.9, ncol=2)
    fig.suptitle("Static sensitivity: constant 2 mm slot, t_c 0.15 mm at every speed (speed-* scenarios)",
                 fontsize=10)
    fig.savefig(path, dpi=DPI)


def bias_figure(path, rpm, panels) -> None:
    """panels: [(title, {label: [bias % per rpm]})]: steady torque bias against spindle speed."""
    fig = Figure(figsize=(9.5, 6.8), dpi=DPI, layout="constrained")
    axes = fig.subplots(len(panels), 1, sharex=True)
    for ax, (title, series) in zip(axes, panels):
        for label, values in series.items():
            style = {"color": "black", "lw": 1.0, "ls": "--"} if label.startswith("correct") else {"lw": 1.4}
            ax.plot(rpm, values, marker="o", label=label, **style)
        ax.axvline(950, color="grey", lw=0.6)
        ax.set_title(title, fontsize=9, loc="left")
        ax.set_ylabel("torque bias (% of truth)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="best", framealpha=0.9)
    axes[-1].set_xlabel("spindle speed (rpm); low-speed gear ≤ 900, high-speed gear ≥ 1000")
    fig.suptitle("One input wrong: steady-cut torque bias at each speed (speed-* scenarios)", fontsize=10)
    fig.savefig(path, dpi=DPI)


def table3_figure(path, grid, points) -> None:
    """grid: {t_c: (R_r array, Table 3 rel err %, exact rel err %)}; points: [(R_r, err %, label)]."""
    fig = Figure(figsize=(8.5, 5.0), dpi=DPI, layout="constrained")
    ax = fig.subplots()
    for t_c, (r_r, poly, exact) in grid.items():
        line = ax.plot(r_r, poly, lw=1.3, label=f"Table 3 polynomial, t_c {t_c} mm")[0]
        ax.plot(r_r, exact, lw=1.0, ls="--", color=line.get_color())
    ax.plot([], [], color="grey", ls="--", label="exact inversion (depth.py), same grid")
    for label, (r_r, err), marker in points:
        ax.plot(r_r, err, ls="none", marker=marker, ms=3, alpha=0.6, label=label)
    ax.set_xlabel("radial immersion R_r = d_r / R")
    ax.set_ylabel("error of R_r from f_x (% of the true R_r)")
    ax.set_ylim(-4, 2)                     # [D]'s own bound, ±10 %, is far outside this scale
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="lower right", framealpha=0.9)
    fig.suptitle("[D] Table 3 polynomial against the exact inversion of eq. 10 (down milling, SB40)", fontsize=10)
    fig.savefig(path, dpi=DPI)
