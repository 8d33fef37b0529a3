"""Issue 13: one revolution's physics on plain floats (`RevolutionPhysics.estimate`, the live daemon's
path: its block closes one revolution) gives the numbers of the columns' path (`estimate_many`, replay's
blocks of many revolutions), in every branch of the chain.

The revolutions are drawn by hypothesis: speeds, powers, f_e missing or 0, a motor-speed channel or
none, speed rises and steps that do or do not count as steady, feed channels, the CNC's override
reported or not, dynamometer and feed-drive forces, tools listed and not. Each configuration turns on
its own branches: the filter gain, the slip-free speed from f_e (pole pairs), the inertia term,
C_f constant and modelled, the depth methods, tools by number. Both forms then run the same
sequence of revolutions, and what they carry between revolutions (the feed check's warning) is
compared too. Whole captures cut into blocks of 1 to 1000 samples, which run both forms on the
same samples: test_vectorised.py.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings as hyp_settings, strategies as st

from millsense.daemon.pipeline.per_revolution import RevolutionColumns, RevolutionMeans, RevolutionPhysics
from tests.estimator import configs

REL = 1e-12   # the same operations in the same order: at most a rounding of a pow or cos apart
ABS = 1e-9    # near zero (terms of a few N·m that cancel), as test_vectorised.py

TOOLS = "\n[tools.7]\ndiameter_mm = 6.0\nflutes = 3\n\n[tools.8]\ndiameter_mm = 12.0\nflutes = 4\ncf = \"model\"\n"

# name: (configuration keywords, has_dynamometer, feed_force)
CASES = {
    "slot, C_f constant, filter, pole pairs": (dict(), False, None),
    "inertia, depth off, no feed configured": (dict(gears=configs.GEARS_WITH_INERTIA, method="off", feed_mm_min=None),
                                               False, None),
    "down, C_f model, known radial": (dict(mode="down", cf="model", radial_depth_mm=4.0, method="torque-only"),
                                      False, None),
    "up, C_f model, no depth": (dict(mode="up", cf="model", method="off"), False, None),
    "feed drive": (dict(mode="down", cf="model"), False, ("feed_i", 120.0, 35.0)),
    "dynamometer, no filter, no pole pairs": (dict(mode="down", filter_cutoff_hz=0.0, pole_pairs=None,
                                                   gears=configs.GEARS_WITH_INERTIA), True, None),
    "tools by number, known axial": (dict(mode="down", axial_depth_mm=5.0, method="torque-only",
                                          extra_toml=TOOLS), False, None),
    # issue 41: the engaged teeth's C_f with a helix, ψ from the estimated axial depth (slot) or the known one
    "slot, C_f auto, 4 flutes, helix": (dict(cf="auto", tool=(16.0, 4, 30.0)), False, None),
    "up, C_f auto, helix, known depths": (dict(mode="up", cf="auto", tool=(16.0, 3, 40.0), radial_depth_mm=10.0,
                                               axial_depth_mm=12.0, method="off"), False, None),
    "down, C_f auto, nothing known": (dict(mode="down", cf="auto", method="off"), False, None),
}


def _settings(tmp_path: Path, name: str):
    kwargs, _, _ = CASES[name]
    kwargs = dict(kwargs)
    extra = kwargs.pop("extra_toml", "")
    path = tmp_path / "one.toml"
    path.write_text(configs.toml_text(**kwargs) + extra)
    from millsense.daemon.config.load import load_config

    return load_config(path)


def _physics(settings, name: str) -> RevolutionPhysics:
    _, dyn, feed_force = CASES[name]
    return RevolutionPhysics(settings, has_dynamometer=dyn, feed_force=feed_force)


def _columns(r: RevolutionMeans) -> RevolutionColumns:
    """One revolution as the columns' path takes it: (1,) arrays, nan for none."""
    def col(v):
        return None if v is None else np.array([v], dtype=float)

    return RevolutionColumns(
        spindle_rpm=np.array([r.spindle_rpm]), p_in_meas_w=np.array([r.p_in_meas_w]),
        p_cu_meas_w=np.array([r.p_cu_meas_w]), p_gap_sq_meas_w2=np.array([r.p_gap_sq_meas_w2]),
        samples=np.array([r.samples], dtype=np.int64),
        f_e_hz=np.array([np.nan if r.f_e_hz is None else r.f_e_hz]),
        motor_rpm=col(r.motor_rpm), feed_rate_mm_min=col(r.feed_rate_mm_min),
        feed_current_a=col(r.feed_current_a), force_x_n=col(r.force_x_n), force_y_n=col(r.force_y_n),
        speed_rise_rpm=np.array([r.speed_rise_rpm]),
        prev_spindle_rpm=np.array([np.nan if r.prev_spindle_rpm is None else r.prev_spindle_rpm]),
        feed_override_pct=col(r.feed_override_pct),
    )


def _maybe(strategy):
    return st.one_of(st.none(), strategy)


@st.composite
def revolutions(draw):
    rpm = draw(st.one_of(st.floats(30.0, 6000.0), st.sampled_from([600.0, 900.0, 1500.0, 4500.0])))
    p_in = draw(st.floats(-500.0, 20000.0))
    p_cu = draw(st.floats(0.0, 2000.0))
    gap = p_in - p_cu
    # the mean of the square: at, above (a cut's ripple) or, by rounding, a hair under the square of the mean
    p_gap_sq = gap * gap * draw(st.sampled_from([1.0, 1.0 - 1e-12])) + draw(st.floats(0.0, 1e6))
    f_e = draw(_maybe(st.one_of(st.floats(1e-3, 400.0), st.just(0.0))))   # none, a drive stopped, turning
    motor = draw(_maybe(st.sampled_from([4.81, 1.157, 2.0, 0.0]).map(lambda g: g * rpm)))
    # a steady spindle, a step inside the speed bands, a ramp or a crash
    rise = draw(st.one_of(st.just(0.0), st.floats(-2.5, 2.5), st.floats(-300.0, 300.0)))
    prev = draw(_maybe(st.one_of(st.just(rpm), st.floats(rpm - 1.0, rpm + 1.0), st.floats(30.0, 6000.0))))
    return RevolutionMeans(
        spindle_rpm=rpm, p_in_meas_w=p_in, p_cu_meas_w=p_cu, p_gap_sq_meas_w2=p_gap_sq,
        samples=draw(st.integers(1, 2000)), f_e_hz=f_e, motor_rpm=motor,
        feed_rate_mm_min=draw(_maybe(st.floats(0.0, 2000.0))), feed_current_a=draw(_maybe(st.floats(0.0, 20.0))),
        force_x_n=draw(_maybe(st.floats(-3000.0, 3000.0))), force_y_n=draw(_maybe(st.floats(-3000.0, 3000.0))),
        speed_rise_rpm=rise, prev_spindle_rpm=prev, feed_override_pct=draw(_maybe(st.floats(0.0, 200.0))),
    )


def _differences(one: dict, many: dict) -> list[str]:
    out = []
    if set(one) != set(many):
        return [f"keys {sorted(set(one) ^ set(many))}"]
    for k, a in one.items():
        b = many[k]
        if type(a) is not type(b):
            out.append(f"{k}: {a!r} ({type(a).__name__}) vs {b!r} ({type(b).__name__})")
        elif isinstance(a, float):
            if not (math.isclose(a, b, rel_tol=REL, abs_tol=ABS) or (math.isnan(a) and math.isnan(b))):
                out.append(f"{k}: {a!r} vs {b!r}")
        elif a != b:
            out.append(f"{k}: {a!r} vs {b!r}")
    return out


@pytest.fixture(scope="module", params=sorted(CASES))
def case(request, tmp_path_factory):
    return request.param, _settings(tmp_path_factory.mktemp("one"), request.param)


@hyp_settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(revs=st.lists(revolutions(), min_size=1, max_size=4), tools=st.lists(st.sampled_from([None, 7, 8, 99]),
                                                                            min_size=4, max_size=4))
def test_one_revolution_on_floats_is_the_columns_path(case, revs, tools):
    name, settings = case
    one, many = _physics(settings, name), _physics(settings, name)
    for k, (r, tool) in enumerate(zip(revs, tools)):
        got = one.estimate(r, tool)
        ref = {f: v[0] for f, v in many.estimate_many(_columns(r), None if tool is None else [tool]).items()}
        diffs = _differences(got, ref)
        assert not diffs, f"{name}, revolution {k} {r}, tool {tool}: " + "; ".join(diffs)
        assert one.last_gain == pytest.approx(many.last_gain, rel=REL) and len(one.gains) == len(many.gains) == 1
        assert one.feed_check.warned == many.feed_check.warned
        assert one.feed_check.take() == many.feed_check.take()


def test_the_cases_reach_their_branches(tmp_path: Path):
    """Each configuration turns on what it is named for (else the comparison above proves less than it says)."""
    seen = {}
    for name in CASES:
        p = _physics(_settings(tmp_path, name), name)
        seen[name] = (p.method, p.cutoff_hz > 0, bool(p.pole_pairs), any(g.inertia_kgm2 for g in p.gears),
                      p.tool.cf_model, sorted(p.tools))
    assert seen["slot, C_f constant, filter, pole pairs"] == ("torque-only", True, True, False, False, [])
    assert seen["inertia, depth off, no feed configured"][:4] == ("off", True, True, True)
    assert seen["down, C_f model, known radial"][0] == "torque-only" and seen["down, C_f model, known radial"][4]
    assert seen["up, C_f model, no depth"][0] == "off" and seen["up, C_f model, no depth"][4]
    assert seen["feed drive"][0] == "feed-drive"
    assert seen["dynamometer, no filter, no pole pairs"][:4] == ("dynamometer", False, False, True)
    assert seen["tools by number, known axial"][0] == "torque-only" and seen["tools by number, known axial"][5] == [7, 8]
