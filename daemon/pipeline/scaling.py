"""Raw DAQ counts -> physical float64 arrays, by channel name.

The DAQ sends signed 16-bit counts and knows nothing of sensors; the
configuration says, per channel name, `physical = (raw - offset) * scale`.
This module binds the configuration to the descriptor the DAQ announced
(which channel sits in which column, of which kind), refuses a descriptor that
lacks a channel the configuration relies on (naming it), and scales whole
blocks at once with one numpy expression.

Roles (which line voltage is `v_uv`, which speed is the spindle's) follow the
channel *names* of the DAQ datasheet (`v_uv`, `i_w`, `sp_rpm`, `mot_rpm`,
`fx`, ...); where a name says nothing, the descriptor's order decides.

The encoder channel carries the low 16 bits of a quadrature count. It is
unwrapped by difference: each step is taken modulo 2^16 into [-32768, 32767],
so any speed below 32768 counts per sample is followed exactly. Across lost
samples the step may hide whole multiples of 2^16 counts; since counts_per_rev
divides 2^16 for every practical encoder, the angle *within* a revolution stays
right, which is what revolution boundaries need.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from millsense.drivers.protocol import ChannelKind, Descriptor

_PHASES = ("u", "v", "w")
_LINES = ("uv", "vw", "wu")


def _config_error(problems: list[str]) -> Exception:
    from millsense.daemon.config.errors import ConfigError  # imported on error only: it pulls in pydantic

    return ConfigError(problems)


@dataclass(frozen=True)
class Roles:
    """Which configured channel plays which part in the physics (None = absent)."""

    voltages: dict[str, str]        # "uv"/"vw"/"wu" -> channel name
    currents: dict[str, str]        # "u"/"v"/"w" -> channel name
    spindle_speed: str | None       # speed channel of the spindle (rpm)
    motor_speed: str | None         # speed channel of the motor (rpm)
    encoder: str | None             # spindle encoder (counts)
    feed_currents: tuple[str, ...]  # feed-drive currents (A)
    feed_rates: tuple[str, ...]     # feed-axis speeds (mm/min)
    forces: dict[str, str]          # "x"/"y"/"z" -> dynamometer channel name (N)


@dataclass(frozen=True)
class LineChannels:
    """The line voltages and currents one descriptor carries, as the sample-level checks read the raw counts
    (the crash check, `safety_check.FrameCheck`; the phase checks, `phase_check.py`): voltages in the order
    uv, vw, wu and currents u, v, w, those present; each with its column and `(raw - offset) * scale`."""

    v_keys: tuple[str, ...]        # of "uv", "vw", "wu"
    i_keys: tuple[str, ...]        # of "u", "v", "w"
    v_names: tuple[str, ...]
    i_names: tuple[str, ...]
    v_cols: tuple[int, ...]
    i_cols: tuple[int, ...]
    v_offsets: tuple[float, ...]
    i_offsets: tuple[float, ...]
    v_scales: tuple[float, ...]
    i_scales: tuple[float, ...]
    i_raw_min: tuple[int, ...]     # the current sensors' limits in counts ([channels.X] raw_min / raw_max)
    i_raw_max: tuple[int, ...]


def line_channels(settings, descriptor: Descriptor) -> LineChannels:
    """The descriptor's line channels. Raises `ConfigError` when the configuration does not fit it."""
    roles = Scaler(settings, descriptor).roles
    channels = dict(settings.channels)
    column = {ch.name: k for k, ch in enumerate(descriptor.channels)}
    v_keys = tuple(k for k in _LINES if k in roles.voltages)
    i_keys = tuple(k for k in _PHASES if k in roles.currents)
    v_names = tuple(roles.voltages[k] for k in v_keys)
    i_names = tuple(roles.currents[k] for k in i_keys)

    def each(names: tuple[str, ...], field: str, kind: type) -> tuple:
        return tuple(kind(getattr(channels[n], field)) for n in names)

    return LineChannels(
        v_keys, i_keys, v_names, i_names, tuple(column[n] for n in v_names), tuple(column[n] for n in i_names),
        each(v_names, "offset", float), each(i_names, "offset", float),
        each(v_names, "scale", float), each(i_names, "scale", float),
        each(i_names, "raw_min", int), each(i_names, "raw_max", int))


def _assign(names: list[str], keys: tuple[str, ...], suffix_of) -> dict[str, str]:
    """Map role keys to names by name suffix first, then by descriptor order."""
    out: dict[str, str] = {}
    rest = []
    for name in names:
        key = suffix_of(name)
        if key in keys and key not in out:
            out[key] = name
        else:
            rest.append(name)
    free = [k for k in keys if k not in out]
    for key, name in zip(free, rest):
        out[key] = name
    return out


def _line_suffix(name: str) -> str | None:
    low = name.lower()
    for line in _LINES:
        if low.endswith(line):
            return line
    return None


def _phase_suffix(name: str) -> str | None:
    low = name.lower()
    return low[-1] if low and low[-1] in _PHASES else None


def _axis_suffix(name: str) -> str | None:
    low = name.lower()
    return low[-1] if low and low[-1] in "xyz" else None


class Scaler:
    """Scales raw blocks of one descriptor into named physical arrays.

    `scale(counts)` returns `{name: float64 array}` for every configured
    channel the descriptor carries; the encoder entry is the unwrapped running
    count (float64, exact up to 2^53 counts). State: only the encoder's last
    raw count and running total, so blocks must be given in order.
    """

    def __init__(self, settings, descriptor: Descriptor):
        self.descriptor = descriptor
        kinds = {ch.name: ch.kind for ch in descriptor.channels}
        column = {ch.name: i for i, ch in enumerate(descriptor.channels)}
        problems: list[str] = []
        configured = dict(settings.channels)
        for name in configured:
            if name not in column:
                problems.append(
                    f"channels.{name}: the DAQ does not send this channel "
                    f"(it sends: {', '.join(descriptor.names) or 'nothing'})"
                )
        used = [ch.name for ch in descriptor.channels if ch.name in configured]
        by_kind: dict[ChannelKind, list[str]] = {}
        for name in used:
            by_kind.setdefault(ChannelKind(kinds[name]), []).append(name)

        speeds = by_kind.get(ChannelKind.SPEED, [])
        motor = [n for n in speeds if n.lower().startswith("mot")]
        spindle = [n for n in speeds if n not in motor]
        encoders = by_kind.get(ChannelKind.ENCODER, [])
        self.roles = Roles(
            voltages=_assign(by_kind.get(ChannelKind.VOLTAGE, []), _LINES, _line_suffix),
            currents=_assign(by_kind.get(ChannelKind.CURRENT, []), _PHASES, _phase_suffix),
            spindle_speed=spindle[0] if spindle else None,
            motor_speed=motor[0] if motor else None,
            encoder=encoders[0] if encoders else None,
            feed_currents=tuple(by_kind.get(ChannelKind.FEED_CURRENT, [])),
            feed_rates=tuple(by_kind.get(ChannelKind.FEED_RATE, [])),
            forces=_assign(by_kind.get(ChannelKind.FORCE, []), ("x", "y", "z"), _axis_suffix),
        )
        r = self.roles
        if len(r.voltages) < 2:
            problems.append(
                "channels: at least two line voltages (voltage channels such as v_uv, v_vw) "
                f"are needed for power; configured and sent: {sorted(r.voltages.values()) or 'none'}"
            )
        if len(r.currents) < 2:
            problems.append(
                "channels: at least two line currents (current channels such as i_u, i_v) "
                f"are needed for power; configured and sent: {sorted(r.currents.values()) or 'none'}"
            )
        if r.encoder is None and r.spindle_speed is None:
            problems.append(
                "channels: the spindle angle needs an encoder channel (sp_enc, with counts_per_rev) "
                "or a spindle speed channel (sp_rpm); neither is configured and sent"
            )
        if r.encoder is not None:
            cpr = getattr(configured[r.encoder], "counts_per_rev", None)
            if not cpr or cpr <= 0:
                problems.append(f"channels.{r.encoder}.counts_per_rev: missing (an encoder needs counts per spindle revolution)")
        for name in getattr(settings, "feed_force", {}) or {}:
            if name not in r.feed_currents:
                problems.append(
                    f"feed_force.{name}: no feed_current channel of that name is configured and sent by the DAQ"
                )
        if problems:
            raise _config_error(problems)

        self.names: tuple[str, ...] = tuple(n for n in used if n != r.encoder)
        self._cols = np.array([column[n] for n in self.names], dtype=np.intp)
        self._offsets = np.array([float(configured[n].offset) for n in self.names])
        self._scales = np.array([float(configured[n].scale) for n in self.names])
        self._enc_col = column[r.encoder] if r.encoder is not None else None
        self.counts_per_rev = float(configured[r.encoder].counts_per_rev) if r.encoder else None
        self._enc_last_raw: int | None = None
        self._enc_total = 0.0

    def scale(self, counts: np.ndarray) -> dict[str, np.ndarray]:
        """One block (n, C) int16 -> {name: (n,) float64}; encoder as running count."""
        phys = (counts[:, self._cols].astype(np.float64) - self._offsets) * self._scales
        out = {name: phys[:, k] for k, name in enumerate(self.names)}
        if self._enc_col is not None:
            out[self.roles.encoder] = self._unwrap(counts[:, self._enc_col])
        return out

    def _unwrap(self, raw: np.ndarray) -> np.ndarray:
        raw64 = raw.astype(np.int64)
        first = self._enc_last_raw if self._enc_last_raw is not None else int(raw64[0])
        steps = np.empty_like(raw64)
        steps[0] = raw64[0] - first
        np.subtract(raw64[1:], raw64[:-1], out=steps[1:])
        steps = (steps + 32768) % 65536 - 32768            # int16 wrap of each step
        running = self._enc_total + np.cumsum(steps, dtype=np.float64)
        self._enc_last_raw = int(raw64[-1])
        self._enc_total = float(running[-1])
        return running
