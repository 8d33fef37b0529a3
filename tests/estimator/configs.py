"""Configuration files for the estimator tests, loaded through the real `load_config`."""

from __future__ import annotations

from pathlib import Path

SIM_CHANNELS = """
[channels.v_uv]
scale = 0.02
[channels.v_vw]
scale = 0.02
[channels.v_wu]
scale = 0.02
[channels.i_u]
scale = 0.002
[channels.i_v]
scale = 0.002
[channels.i_w]
scale = 0.002
[channels.sp_rpm]
scale = 0.1
"""

ENCODER = """
[channels.sp_enc]
scale = 1.0
counts_per_rev = 4096
"""

GEARS = """
[[gears]]
name = "low-speed"
ratio = 4.81
max_spindle_rpm = 900
friction_torque_nm = 2.6629
viscous_nms = 0.0400

[[gears]]
name = "high-speed"
ratio = 1.157
max_spindle_rpm = 4500
friction_torque_nm = 1.6160
viscous_nms = 0.0022
"""

# The simulated machine's rotating masses referred to the spindle (machine data, like the friction
# above: sim/machine.py, rotor_inertia·ratio² + spindle_inertia).
PLANT_INERTIA_KGM2 = {"low-speed": 0.06 * 4.81**2 + 0.08, "high-speed": 0.06 * 1.157**2 + 0.08}
GEARS_WITH_INERTIA = (GEARS.replace("viscous_nms = 0.0400\n", f"viscous_nms = 0.0400\ninertia_kgm2 = {PLANT_INERTIA_KGM2['low-speed']}\n")
                      .replace("viscous_nms = 0.0022\n", f"viscous_nms = 0.0022\ninertia_kgm2 = {PLANT_INERTIA_KGM2['high-speed']}\n"))


def toml_text(
    *,
    filter_cutoff_hz: float = 200.0,
    encoder: bool = True,
    drop: tuple[str, ...] = (),
    extra_channels: str = "",
    winding: str = "delta",
    pole_pairs: int | None = 2,
    tool: tuple[float, int] | tuple[float, int, float] = (20.0, 2),   # (diameter, flutes[, helix_deg])
    cf: float | str = 1.075,
    material: tuple[float, ...] = (760.0, -0.40, 0.25, -0.25, 0.12, 0.17),
    mode: str = "slot",
    feed_mm_min: float | None = 200.0,
    axial_depth_mm: float | None = None,
    radial_depth_mm: float | None = None,
    method: str = "auto",
    min_torque_nm: float = 0.5,
    feed_force: str = "",
    gears: str = GEARS,
    edge_n_mm: tuple[float, float] | None = None,   # [material] edge_t_n_mm, edge_r_n_mm (physics.md §5b)
) -> str:
    channels = SIM_CHANNELS + (ENCODER if encoder else "") + extra_channels
    for name in drop:
        channels = channels.replace(f"[channels.{name}]\nscale = {0.02 if name.startswith('v') else 0.002}\n", "")
    cut = [f'mode = "{mode}"']
    if feed_mm_min is not None:
        cut.append(f"feed_mm_min = {feed_mm_min}")
    if axial_depth_mm is not None:
        cut.append(f"axial_depth_mm = {axial_depth_mm}")
    if radial_depth_mm is not None:
        cut.append(f"radial_depth_mm = {radial_depth_mm}")
    cf_text = f'"{cf}"' if isinstance(cf, str) else str(cf)
    ks, ks_exp, r1, r1_exp, r2, r2_exp = material
    motor = f'winding = "{winding}"\nstator_resistance_ohm = 0.349\n'
    if pole_pairs is not None:
        motor += f"pole_pairs = {pole_pairs}\n"
    return f"""
machine = "test-mill"

[daq]
transport = "sim"
scenario = "step"
filter_cutoff_hz = {filter_cutoff_hz}
filter_order = 2
{channels}
[motor]
{motor}
{gears}
[tool]
diameter_mm = {tool[0]}
flutes = {tool[1]}
cf = {cf_text}
{f"helix_deg = {tool[2]}" if len(tool) > 2 else ""}

[material]
ks = {ks}
ks_exp = {ks_exp}
r1 = {r1}
r1_exp = {r1_exp}
r2 = {r2}
r2_exp = {r2_exp}
{"" if edge_n_mm is None else f"edge_t_n_mm = {edge_n_mm[0]}{chr(10)}edge_r_n_mm = {edge_n_mm[1]}"}

[cut]
{chr(10).join(cut)}

[depth]
method = "{method}"
min_torque_nm = {min_torque_nm}

[feed_force]
{feed_force}
"""


def load(tmp_path: Path, name: str = "test.toml", **kwargs):
    from millsense.daemon.config.load import load_config

    path = tmp_path / name
    path.write_text(toml_text(**kwargs))
    return load_config(path)
