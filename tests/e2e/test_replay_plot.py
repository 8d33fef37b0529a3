"""`millsense replay --plot OUT.png` on real subprocesses: a PNG in addition, the JSON lines unchanged.

The missing-extra case is caused the only way a test can cause it while
matplotlib is installed: a PYTHONPATH shim whose `matplotlib` raises
ImportError on import, exactly what Python does when the package is absent.
"""

from __future__ import annotations

import os
import struct
import subprocess

import pytest

from tests.e2e.helpers import CMD, write_config

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def replay_inputs(step_capture, tmp_path_factory):
    cap, _ = step_capture
    cfg = write_config(tmp_path_factory.mktemp("plot") / "p.toml", machine="plot-01",
                       daq='transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = 1',
                       alarms="torque_warn_nm = 1.5\ntorque_limit_nm = 3.0")
    return cap, cfg


def _replay(cap, cfg, *extra, env=None):
    return subprocess.run(CMD + ["replay", str(cap), "--config", str(cfg), *extra],
                          capture_output=True, text=True, timeout=120, env=env)


def _broken_matplotlib_env(tmp_path):
    shim = tmp_path / "shim" / "matplotlib"
    shim.mkdir(parents=True)
    (shim / "__init__.py").write_text('raise ImportError("No module named \'matplotlib\' (test shim)")\n')
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(shim.parent), env.get("PYTHONPATH", "")) if p)
    return env


def test_plot_writes_a_png_and_leaves_the_json_lines_unchanged(replay_inputs, tmp_path):
    pytest.importorskip("matplotlib", reason="the plot extra (pip install 'millsense[plot]') is not installed")
    cap, cfg = replay_inputs
    plain = _replay(cap, cfg)
    out = tmp_path / "run.png"
    plotted = _replay(cap, cfg, "--plot", str(out))
    assert plain.returncode == 0, plain.stderr
    assert plotted.returncode == 0, plotted.stderr
    assert plotted.stdout == plain.stdout and '"type":"alarm"' in plain.stdout   # alarms to mark
    data = out.read_bytes()
    assert data[:8] == PNG_SIGNATURE and data[12:16] == b"IHDR"
    width, height = struct.unpack(">II", data[16:24])
    assert width >= 600 and height >= 400, (width, height)
    assert len(data) < 300_000, f"{len(data)} bytes: not a modest PNG"
    assert f"wrote {out}" in plotted.stderr


def test_missing_matplotlib_is_one_clear_line_and_no_output(replay_inputs, tmp_path):
    cap, cfg = replay_inputs
    out = tmp_path / "run.png"
    p = _replay(cap, cfg, "--plot", str(out), env=_broken_matplotlib_env(tmp_path))
    assert p.returncode == 1
    assert p.stdout == ""                                    # failed before reading the capture
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1, p.stderr
    assert "matplotlib" in lines[0] and "pip install 'millsense[plot]'" in lines[0]
    assert "Traceback" not in p.stderr
    assert not out.exists()


def test_replay_without_plot_never_imports_matplotlib(replay_inputs, tmp_path):
    cap, cfg = replay_inputs
    p = _replay(cap, cfg, env=_broken_matplotlib_env(tmp_path))
    assert p.returncode == 0, p.stderr
    assert '"type":"estimate"' in p.stdout


def test_plot_into_a_missing_directory_fails_before_output(replay_inputs, tmp_path):
    cap, cfg = replay_inputs
    p = _replay(cap, cfg, "--plot", str(tmp_path / "no" / "such" / "run.png"))
    assert p.returncode == 1 and p.stdout == ""
    if "matplotlib" not in p.stderr:                         # with the extra: the directory is the error
        assert "no such directory" in p.stderr
    assert "Traceback" not in p.stderr


def test_the_rpm_axis_shows_rpm_not_an_offset(replay_inputs):
    # Issue 39: a spindle held at 600 rpm spans a fraction of an rpm, and matplotlib's default formatter
    # labelled the axis `+5.999e2` with ticks 0.01, 0.02, ... The figure of the replay's own payloads (the
    # subprocess's JSON lines), drawn, then its tick labels read.
    pytest.importorskip("matplotlib", reason="the plot extra (pip install 'millsense[plot]') is not installed")
    import json

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from millsense.daemon.plot import ReplayPlot

    cap, cfg = replay_inputs
    p = _replay(cap, cfg)
    assert p.returncode == 0, p.stderr
    plot = ReplayPlot()
    for line in p.stdout.splitlines():
        plot.add(json.loads(line))
    rpm = [e["spindle_rpm"] for e in plot.estimates if e.get("spindle_rpm") is not None]
    assert rpm and max(rpm) - min(rpm) < 0.01 * min(rpm), "a steady spindle: the case the offset took"

    fig = plot.figure("test")
    FigureCanvasAgg(fig).draw()
    rpm_axis = fig.axes[0].yaxis
    assert rpm_axis.get_major_formatter().get_offset() == ""
    assert rpm_axis.get_offset_text().get_text() == ""
    shown = [float(t.get_text().replace("\u2212", "-")) for t in rpm_axis.get_ticklabels() if t.get_text()]
    low, high = fig.axes[0].get_ylim()
    inside = [v for v in shown if low <= v <= high]
    assert inside, shown
    assert all(0.5 * min(rpm) <= v <= 1.5 * max(rpm) for v in inside), (shown, min(rpm), max(rpm))
    # Every panel reads in its own unit (torque, force and depth too).
    assert [ax.yaxis.get_offset_text().get_text() for ax in fig.axes] == [""] * len(fig.axes)
