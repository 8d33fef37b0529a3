"""Pure, vectorised physics of millsense: samples → power → torque → force → depth.

One module per step, each formula beside its equation number in the source
papers ([P] spindle power → force; [D] average forces → depth of cut); see
``docs/physics.md``. No I/O, no state: numpy arrays or scalars in and out.

- ``power``: stator power, phase currents, copper loss, electrical frequency,
  anti-alias filter gain, air-gap power ([P] eq. 11)
- ``torque``: cutting torque ([P] eq. 13), gear selection, σ ([P] eq. 20)
- ``force``: resultant force ([P] eq. 18), C_f of the engaged teeth (η·√(1 + r₁(t_a)²))
- ``resultant``: the engaged teeth's forces added as vectors (η, a table per flute count)
- ``materials``: ISO material groups from published k_c1.1 / m_c
- ``milling``: average forces of end milling ([D] eqs. 7–10, 12), down/up/slot
- ``depth``: exact inversions with a status ([D] §3)
- ``validity``: where a depth and a cut may be claimed at all (feed per tooth,
  speed, the tool's geometry, a spindle running up or braking)
- ``calibration``: least-squares friction, J and C_f ([P] §4.2), a material from a test cut
- ``expected``: the load a programmed cut should take (the milling model run forwards)
- ``table3``: [D] Table 3 polynomial, for comparison only
- ``numbers``: one formula for a plain float (the live revolution) and arrays
"""
