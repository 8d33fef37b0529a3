"""[D] §3: exact inversion of eqs. (10), (12), (13), with statuses."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from millsense.daemon.physics import depth
from millsense.daemon.physics.depth import (
    MIN_RADIAL_RATIO,
    depth_from_torque,
    depths_from_forces,
    radial_ratio_from_fx,
    radial_ratio_from_fxt,
)
from millsense.daemon.physics.milling import (
    NP,
    SB40_TABLE2,
    SCALAR,
    _ratios_xp,
    average_forces_n,
    force_ratio_fx,
    force_ratio_fxt,
)

pytestmark = pytest.mark.quick

M = SB40_TABLE2
RADIUS_MM, FLUTES = 8.0, 4
feeds = st.floats(0.01, 0.7)


def forward(r_r, r_a, t_c, mode):
    f = average_forces_n(r_r, r_a, t_c, RADIUS_MM, FLUTES, M, mode)
    return float(f.tangential_n), float(f.x_n), float(f.y_n)


def count_roots_on_fine_grid(curve, target):
    """Independent check: sign changes of curve − target on a fine grid over the model's domain."""
    grid = np.geomspace(MIN_RADIAL_RATIO, 2.0, 20001)
    d = curve(grid) - target
    # A grid point within rounding of the target is a root of its own (a run of them one root): the ends
    # above all, where no sign change can show it (r_r = 2 evaluated on an array lands 1e-17 off the scalar).
    near = np.abs(d) <= 1e-12 * max(1.0, abs(target))
    s = np.sign(np.where(near, 0.0, d))
    changes = int(np.count_nonzero(s[1:] * s[:-1] < 0))
    runs_of_near = int(np.count_nonzero(near[1:] & ~near[:-1])) + int(near[0])
    return changes + runs_of_near


@settings(max_examples=80, deadline=None)
@given(r_r=st.floats(0.05, 2.0), r_a=st.floats(0.05, 4.0), t_c=feeds)
@example(r_r=2.0, r_a=1.5, t_c=0.390625)  # found by hypothesis: f_x at the branch end, off in the last bit
def test_dynamometer_round_trip_down_milling(r_r, r_a, t_c):
    f_t, f_x, f_y = forward(r_r, r_a, t_c, "down")
    res = depths_from_forces(fx_n=f_x, fy_n=f_y, feed_per_tooth_mm=t_c, tool_radius_mm=RADIUS_MM, flutes=FLUTES, material=M, mode="down")
    assert res.status == "ok"
    assert res.radial_depth_mm / RADIUS_MM == pytest.approx(r_r, abs=1e-6)
    assert res.axial_depth_mm / RADIUS_MM == pytest.approx(r_a, rel=1e-6)


@settings(max_examples=80, deadline=None)
@given(r_r=st.floats(MIN_RADIAL_RATIO * 1.001, 2.0), r_a=st.floats(0.05, 4.0), t_c=feeds)
@example(r_r=2.0, r_a=1.5, t_c=0.390625)
def test_feed_drive_round_trip_down_milling(r_r, r_a, t_c):
    f_t, f_x, _ = forward(r_r, r_a, t_c, "down")
    res = depths_from_forces(tangential_n=f_t, feed_n=f_x, feed_per_tooth_mm=t_c, tool_radius_mm=RADIUS_MM, flutes=FLUTES, material=M, mode="down")
    assert res.status == "ok"
    assert res.radial_depth_mm / RADIUS_MM == pytest.approx(r_r, abs=1e-6)
    assert res.axial_depth_mm / RADIUS_MM == pytest.approx(r_a, rel=1e-6)


@settings(max_examples=60, deadline=None)
@given(r_r=st.floats(MIN_RADIAL_RATIO * 1.001, 2.0), r_a=st.floats(0.05, 4.0), t_c=feeds, mode=st.sampled_from(["down", "up"]))
def test_torque_only_round_trip(r_r, r_a, t_c, mode):
    f_t, _, _ = forward(r_r, r_a, t_c, mode)
    torque_nm = f_t * RADIUS_MM * 1e-3
    by_axial = depth_from_torque(torque_nm, t_c, RADIUS_MM, FLUTES, M, mode, known_axial_mm=r_a * RADIUS_MM)
    assert by_axial.status == "ok"
    assert by_axial.radial_depth_mm / RADIUS_MM == pytest.approx(r_r, abs=1e-6)
    assert by_axial.axial_depth_mm == pytest.approx(r_a * RADIUS_MM)
    by_radial = depth_from_torque(torque_nm, t_c, RADIUS_MM, FLUTES, M, mode, known_radial_mm=r_r * RADIUS_MM)
    assert by_radial.status == "ok"
    assert by_radial.axial_depth_mm / RADIUS_MM == pytest.approx(r_a, rel=1e-9)


@settings(max_examples=60, deadline=None)
@given(r_r=st.floats(MIN_RADIAL_RATIO * 1.001, 2.0), t_c=feeds, mode=st.sampled_from(["down", "up"]), kind=st.sampled_from(["fx", "fxt"]))
@example(r_r=2.0, t_c=0.17987216858192062, mode="up", kind="fx")  # a root at the end and one at 1.9963
def test_status_agrees_with_an_independent_root_count(r_r, t_c, mode, kind):
    """ok ⇔ the measured ratio has one preimage over [MIN_RADIAL_RATIO, 2]; unresolvable ⇔ several."""
    ratio = force_ratio_fx if kind == "fx" else force_ratio_fxt
    solve = radial_ratio_from_fx if kind == "fx" else radial_ratio_from_fxt
    target = float(ratio(r_r, t_c, M, mode))
    roots = count_roots_on_fine_grid(lambda g: ratio(g, t_c, M, mode), target)
    assume(roots >= 1)  # two roots closer than the grid's step are not seen: skip those
    got, status = solve(target, t_c, M, mode)
    if roots == 1:
        assert status == "ok" and got == pytest.approx(r_r, abs=1e-6)
    else:
        assert status == "unresolvable" and got is None


@settings(max_examples=40, deadline=None)
@given(r_r=st.floats(1.5, 1.99), t_c=feeds)
def test_up_milling_fxt_resolves_wide_immersions(r_r, t_c):
    """Up milling f_xt rises then falls; wide immersions sit on the falling branch alone.
    (Within ~1e-3 of R_r = 2 it dips and rises again — t_a falls as the exit angle nears π —
    so values there have two preimages ~1e-3 apart and are reported unresolvable.)"""
    got, status = radial_ratio_from_fxt(float(force_ratio_fxt(r_r, t_c, M, "up")), t_c, M, "up")
    assert status == "ok" and got == pytest.approx(r_r, abs=1e-6)


@settings(max_examples=60, deadline=None)
@given(r_r=st.floats(0.001, 2.0), t_c=st.floats(0.001, 1.0), mode=st.sampled_from(["down", "up", "slot"]))
def test_scalar_kernel_equals_vectorised_model(r_r, t_c, mode):
    """The root finder runs the shared formulas on math floats; they must equal numpy's."""
    s = _ratios_xp(SCALAR, r_r, t_c, M, mode)
    v = _ratios_xp(NP, np.float64(r_r), np.float64(t_c), M, mode)
    np.testing.assert_allclose(s, v, rtol=1e-12, atol=1e-15)


def test_fx_turnover_region_is_unresolvable():
    t_c = 0.1042
    just_above_floor = float(force_ratio_fx(0.012, t_c, M, "down"))
    r_r, status = radial_ratio_from_fx(just_above_floor, t_c, M, "down")
    assert (r_r, status) == (None, "unresolvable")


def test_ratios_beyond_the_model_are_out_of_range():
    t_c = 0.1042
    slot_fx = float(force_ratio_fx(2.0, t_c, M, "down"))
    minimum_fx = float(np.min(force_ratio_fx(np.geomspace(0.005, 0.05, 2000), t_c, M, "down")))
    assert radial_ratio_from_fx(slot_fx + 0.01, t_c, M, "down") == (None, "out_of_range")
    assert radial_ratio_from_fx(minimum_fx - 0.01, t_c, M, "down") == (None, "out_of_range")
    assert radial_ratio_from_fx(1.5, t_c, M, "down") == (None, "out_of_range")
    assert radial_ratio_from_fxt(float(force_ratio_fxt(2.0, t_c, M, "down")) + 0.01, t_c, M, "down") == (None, "out_of_range")
    assert radial_ratio_from_fx(float("nan"), t_c, M, "down") == (None, "out_of_range")
    assert radial_ratio_from_fxt(0.0, 0.0, M, "down") == (None, "out_of_range")  # no feed: no chip
    # the slot value itself is the end of the range, not beyond it
    r_r, status = radial_ratio_from_fx(slot_fx, t_c, M, "down")
    assert status == "ok" and r_r == pytest.approx(2.0)


def test_normal_force_of_the_wrong_sign_is_out_of_range():
    """f_x ignores the sign of F_y; the model does not (down milling pushes the tool to −y)."""
    _, f_x, f_y = forward(0.5, 1.0, 0.1, "down")
    kw = dict(feed_per_tooth_mm=0.1, tool_radius_mm=RADIUS_MM, flutes=FLUTES, material=M, mode="down")
    assert f_y < 0
    assert depths_from_forces(fx_n=f_x, fy_n=f_y, **kw).status == "ok"
    assert depths_from_forces(fx_n=f_x, fy_n=-f_y, **kw).status == "out_of_range"


def test_torque_beyond_the_model_is_out_of_range():
    t_c, axial_mm = 0.1, 4.0
    f_t_slot, _, _ = forward(2.0, axial_mm / RADIUS_MM, t_c, "down")
    too_much = 1.05 * f_t_slot * RADIUS_MM * 1e-3
    assert depth_from_torque(too_much, t_c, RADIUS_MM, FLUTES, M, "down", known_axial_mm=axial_mm).status == "out_of_range"
    f_t_floor, _, _ = forward(MIN_RADIAL_RATIO, axial_mm / RADIUS_MM, t_c, "down")
    too_little = 0.5 * f_t_floor * RADIUS_MM * 1e-3
    assert depth_from_torque(too_little, t_c, RADIUS_MM, FLUTES, M, "down", known_axial_mm=axial_mm).status == "out_of_range"


def test_air_cut_and_missing_second_force():
    kw = dict(feed_per_tooth_mm=0.1, tool_radius_mm=RADIUS_MM, flutes=FLUTES, material=M, mode="down")
    assert depths_from_forces(fx_n=0.0, fy_n=0.0, **kw).status == "air_cut"
    assert depths_from_forces(tangential_n=-3.0, feed_n=1.0, **kw).status == "air_cut"
    assert depths_from_forces(tangential_n=30.0, feed_n=1.0, min_force_n=50.0, **kw).status == "air_cut"
    assert depths_from_forces(tangential_n=300.0, **kw) == (None, None, "no_second_force")
    assert depths_from_forces(**kw).status == "no_second_force"
    assert depth_from_torque(0.0, 0.1, RADIUS_MM, FLUTES, M, "down", known_axial_mm=4.0).status == "air_cut"
    assert depth_from_torque(0.4, 0.1, RADIUS_MM, FLUTES, M, "down", known_axial_mm=4.0, min_torque_nm=0.5).status == "air_cut"
    assert depth_from_torque(3.0, 0.1, RADIUS_MM, FLUTES, M, "down").status == "no_second_force"


def test_slot_needs_only_the_torque():
    t_c, r_a = 0.05, 0.25
    f_t, _, _ = forward(2.0, r_a, t_c, "slot")
    res = depth_from_torque(f_t * RADIUS_MM * 1e-3, t_c, RADIUS_MM, FLUTES, M, "slot")
    assert res.status == "ok"
    assert res.radial_depth_mm == pytest.approx(2 * RADIUS_MM)
    assert res.axial_depth_mm == pytest.approx(r_a * RADIUS_MM, rel=1e-9)
    res = depths_from_forces(tangential_n=f_t, feed_per_tooth_mm=t_c, tool_radius_mm=RADIUS_MM, flutes=FLUTES, material=M, mode="slot")
    assert res.axial_depth_mm == pytest.approx(r_a * RADIUS_MM, rel=1e-9)


def test_bad_arguments_raise_clear_errors():
    with pytest.raises(ValueError, match="not both"):
        depth_from_torque(3.0, 0.1, RADIUS_MM, FLUTES, M, "down", known_radial_mm=2.0, known_axial_mm=4.0)
    with pytest.raises(ValueError, match="outside"):
        depth_from_torque(3.0, 0.1, RADIUS_MM, FLUTES, M, "down", known_radial_mm=20.0)
    with pytest.raises(ValueError, match="mode"):
        radial_ratio_from_fx(0.1, 0.1, M, "sideways")
    with pytest.raises(ValueError, match="radius"):
        depths_from_forces(tangential_n=1.0, feed_n=1.0, feed_per_tooth_mm=0.1, tool_radius_mm=0.0, flutes=4, material=M, mode="down")


@pytest.mark.serial
def test_solve_is_fast_enough_for_every_revolution():
    """Generous sanity bound only (bench/physics_table3.py prints the real figure)."""
    depth._branches.cache_clear()
    rng = np.random.default_rng(5)
    t_c = rng.uniform(0.02, 0.5, 100)
    targets = [float(force_ratio_fx(r, t, M, "down")) for r, t in zip(rng.uniform(0.1, 2.0, 100), t_c)]
    start = time.perf_counter()
    for f, t in zip(targets, t_c):
        assert radial_ratio_from_fx(f, t, M, "down")[1] == "ok"
    assert (time.perf_counter() - start) / 100 < 5e-3


# --- the root finder that replaced scipy.optimize.brentq in the daemon ---------------------


@settings(max_examples=200, deadline=None)
@given(r_r=st.floats(MIN_RADIAL_RATIO, 2.0), t_c=feeds, kind=st.sampled_from(["fx", "fxt"]))
def test_bracketed_root_agrees_with_scipy_brentq(r_r, t_c, kind):
    """Every branch solve of the depth model, ours against scipy's, to 1e-9 relative."""
    from scipy.optimize import brentq  # the reference; tests may import scipy, the daemon does not

    curve = depth._curve(kind, t_c, M, "down", 1.0, 1.0)
    target = float(curve(SCALAR, r_r))
    for br in depth._branches(kind, t_c, M, "down"):
        g = lambda r: curve(SCALAR, r) - target  # noqa: E731
        if g(br.r_lo) * g(br.r_hi) >= 0.0:
            continue
        ours = depth.bracketed_root(g, br.r_lo, br.r_hi, xtol=1e-14)
        ref = brentq(g, br.r_lo, br.r_hi, xtol=1e-14, rtol=4 * np.finfo(float).eps)
        assert ours == pytest.approx(ref, rel=1e-9, abs=1e-14)


@pytest.mark.parametrize(
    "f, a, b",
    [
        (lambda x: x**3 - 2.0 * x - 5.0, 2.0, 3.0),          # a smooth simple root
        (lambda x: np.cbrt(x - 0.3), -1.0, 2.0),             # infinite slope at the root: bisection must carry it
        (lambda x: 1.0 if x > 0.7 else -1.0, 0.0, 1.0),      # a step: only bisection converges
        (lambda x: np.exp(x) - 1e6, 0.0, 50.0),              # very uneven curvature
    ],
)
def test_bracketed_root_hard_cases_match_brentq(f, a, b):
    from scipy.optimize import brentq

    ours = depth.bracketed_root(f, a, b)
    ref = brentq(f, a, b)
    assert ours == pytest.approx(ref, rel=1e-9, abs=4e-12)


def test_bracketed_root_gives_up_where_brentq_does():
    """A triple root: f is flat to below the tolerance's reach, both stop at the iteration limit."""
    from scipy.optimize import brentq

    f = lambda x: (x - 0.2) ** 3  # noqa: E731
    with pytest.raises(RuntimeError):
        brentq(f, -1.0, 1.0)
    with pytest.raises(RuntimeError, match="no convergence"):
        depth.bracketed_root(f, -1.0, 1.0)


def test_bracketed_root_refuses_a_bracket_without_a_sign_change():
    with pytest.raises(ValueError, match="no sign change"):
        depth.bracketed_root(lambda x: x * x + 1.0, -1.0, 1.0)
    assert depth.bracketed_root(lambda x: x - 2.0, 2.0, 5.0) == 2.0   # a root at an end is that end


def test_the_live_daemon_does_not_import_scipy_optimize():
    """A fresh interpreter that builds the live pipeline must not load scipy.optimize (45 MB, 0.4 s)."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import numpy as np\n"
        "import millsense.daemon.commands.run\n"
        "from millsense.daemon.config.load import demo_config\n"
        "from millsense.daemon.pipeline.run_core import PipelineCore\n"
        "from millsense.drivers.base import SampleBlock\n"
        "from millsense.drivers.protocol import Channel, ChannelKind as K, Descriptor\n"
        "kinds = [K.VOLTAGE] * 3 + [K.CURRENT] * 3 + [K.SPEED, K.ENCODER]\n"
        "names = ['v_uv', 'v_vw', 'v_wu', 'i_u', 'i_v', 'i_w', 'sp_rpm', 'sp_enc']\n"
        "core = PipelineCore(demo_config())\n"
        "core.on_descriptor(Descriptor(1000, tuple(map(Channel, kinds, names))))\n"
        "core.process(SampleBlock(0, 0, np.ones((500, 8), np.int16), 0, False))\n"
        "print(sorted(m for m in sys.modules if m.startswith('scipy.optimize')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
