"""The pydantic model of the millsense TOML file (interfaces.md, "Configuration file").

Field names are the TOML keys, units are in the names, every model forbids
unknown keys (a typo must fail at start, not silently take a default) and is
strict (``flutes = "2"`` or ``flutes = 2.5`` is refused rather than coerced).
A section left out takes all its defaults; an alarm limit left out is an alarm
not armed.

Checks inside one section live here (they can see only that section) and report
*every* problem they find at once through `problems_error`; checks across
sections, the calibration file and the DAQ descriptor are in `checks`.
"""

from __future__ import annotations

import ipaddress
import json
import math
import re
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, SecretStr, model_validator
from pydantic_core import PydanticCustomError

MACHINE_PATTERN = r"^[A-Za-z0-9_-]+$"
CHANNEL_NAME_PATTERN = r"^[A-Za-z0-9_]{1,8}$"  # daq-protocol.md: ≤ 8 ASCII letters, digits, '_'
# [P] found 1.03–1.11; √(1+r1²) for r1 ≤ 1.1 stays below 1.5. With several teeth in cut the forces add as
# vectors and C_f falls to π/4·√(1+r1²) in a many-flute slot (physics/resultant.py): 0.75 admits a fitted one.
CF_RANGE = (0.75, 1.5)
TRANSPORTS = ("serial", "tcp", "modbus-tcp", "modbus-rtu", "sim")

# Zenoh endpoints: <protocol>/<address>[?metadata][#config]
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_ENDPOINT_RE = re.compile(r"^(?P<proto>[a-z][a-z0-9-]*)/(?P<addr>[^?#]+)(?P<rest>[?#].*)?\Z")
_HOST_PORT_RE = re.compile(r"^(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+):(?P<port>[0-9]{1,5})\Z")


def problems_error(problems: list[tuple[str, str]]) -> PydanticCustomError:
    """One pydantic error carrying several `(key, "what is wrong (expected)")` problems.

    A validator can raise only one error; this keeps all of a section's
    problems, and `errors` expands them under the section's location.
    """
    return PydanticCustomError("millsense_problems", "{count} problem(s)", {"count": len(problems), "problems": problems})


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, frozen=False)


# --------------------------------------------------------------------------- [daq]
MIN_FILTER_CUTOFF_HZ = 1.0


def _filter_cutoff(value: float) -> float:
    """0 (no filter to divide out) or a real analog anti-alias filter's cutoff: at least 1 Hz and finite.
    Far below it the gain divided out at f_e, 1/(1 + (f_e/f_c)^(2n)), underflows (an inf power)."""
    if value == 0:
        return value
    if not math.isfinite(value) or value < MIN_FILTER_CUTOFF_HZ:
        raise ValueError(f"{value!r} is below any real anti-alias filter "
                         f"(0 = no filter to divide out, else a cutoff of at least {MIN_FILTER_CUTOFF_HZ:g} Hz)")
    return value


class DaqSettings(_Section):
    """`[daq]`: which transport reaches the DAQ, and the DAQ's analog filter.

    serial / modbus-rtu need `port`; tcp / modbus-tcp need `host` and `tcp_port`;
    sim takes `scenario` (default "step"). Keys of other transports may be
    present and are ignored, as in the interfaces.md example.
    """

    transport: Literal["serial", "tcp", "modbus-tcp", "modbus-rtu", "sim"]
    port: str | None = None
    baudrate: int = Field(921600, gt=0)
    host: str | None = None
    tcp_port: int | None = Field(None, ge=1, le=65535)
    unit: int = Field(1, ge=0, le=247)
    scenario: str | None = None
    poll_ms: int = Field(20, ge=1, le=10000)
    timeout_ms: int = Field(200, ge=10, le=10000)  # modbus: one try of one request (additive key)
    # The rate the DAQ is wired and set for (additive key). A DESCRIPTOR that claims
    # another rate is refused as fault `descriptor`: every speed and torque would scale with it.
    sample_rate_hz: int = Field(1000, ge=1, le=65535)
    # The samples' arrival on the host's clock against that rate (rate_check.py; additive key). Off only
    # for a stream sent faster than real time on purpose (a recorded part played at speed on a test bench).
    check_sample_rate: bool = True
    filter_cutoff_hz: Annotated[float, AfterValidator(_filter_cutoff)] = 200.0  # 0 = no anti-alias filter to divide out
    filter_order: int = Field(2, ge=1, le=8)

    @model_validator(mode="after")
    def _transport_needs(self) -> DaqSettings:
        problems: list[tuple[str, str]] = []
        t = self.transport
        if t in ("serial", "modbus-rtu") and not self.port:
            problems.append(("port", f'missing (transport "{t}" needs a serial device, e.g. "/dev/ttyACM0")'))
        if t in ("tcp", "modbus-tcp"):
            if not self.host:
                problems.append(("host", f'missing (transport "{t}" needs the DAQ\'s host name or IP address)'))
            if self.tcp_port is None:
                problems.append(("tcp_port", f"missing (transport \"{t}\" needs a TCP port, 1–65535{', usually 502' if t == 'modbus-tcp' else ''})"))
        if t == "modbus-rtu":
            # the longest answer, 125 registers: 255 bytes of 11 bits (start, 8 data, parity/stop, stop)
            answer_ms = 255 * 11 / self.baudrate * 1e3
            if self.timeout_ms < 2 * answer_ms:
                problems.append(("timeout_ms", f"{self.timeout_ms} is too short for a 125-register answer at {self.baudrate} "
                                               f"baud ({answer_ms:.0f} ms on the wire; at least {2 * answer_ms:.0f})"))
        if problems:
            raise problems_error(problems)
        if t == "sim" and not self.scenario:
            self.scenario = "step"
        return self


# --------------------------------------------------------------------------- [channels.*]
def _nonzero(value: float) -> float:
    if value == 0:
        raise ValueError("must not be 0 (a non-zero number: physical = (raw - offset) * scale)")
    return value


class ChannelSettings(_Section):
    """`[channels.NAME]`: physical = (raw − offset) · scale, in the unit of the channel's kind.

    `counts_per_rev` is for an encoder channel (counts per spindle revolution).
    `raw_min` / `raw_max` (additive) are the raw counts at which the channel's
    ADC or sensor saturates (default: the int16 range); a sample at or beyond
    either is clipped, not measured.
    """

    scale: Annotated[float, AfterValidator(_nonzero)] = 1.0
    offset: float = 0.0
    counts_per_rev: int | None = Field(None, ge=1)
    raw_min: int = Field(-32768, ge=-32768, le=32767)
    raw_max: int = Field(32767, ge=-32768, le=32767)

    @model_validator(mode="after")
    def _raw_range(self) -> ChannelSettings:
        if self.raw_min >= self.raw_max:
            raise problems_error([("raw_max", f"{self.raw_max} is not above raw_min = {self.raw_min} (the ADC's highest count)")])
        return self


ChannelName = Annotated[str, Field(pattern=CHANNEL_NAME_PATTERN)]


# --------------------------------------------------------------------------- [motor], [[gears]]
class MotorSettings(_Section):
    """`[motor]`: the spindle motor's winding and stator resistance per phase ([P] Table 2)."""

    winding: Literal["delta", "wye"]
    stator_resistance_ohm: float = Field(gt=0)
    pole_pairs: int | None = Field(None, ge=1)  # with it the gear follows from f_e / spindle speed


class GearSettings(_Section):
    """`[[gears]]`: one gear, friction referred to the spindle ([P] eq. 13).

    `friction_torque_nm` (T_f') and `viscous_nms` (B') default to 0 until
    `millsense calibrate` fits them; the calibration file overrides them by name.
    """

    name: str = Field(min_length=1)
    ratio: float = Field(gt=0)  # motor speed / spindle speed
    max_spindle_rpm: float = Field(gt=0)
    friction_torque_nm: float = Field(0.0, ge=0)
    viscous_nms: float = Field(0.0, ge=0)
    # J of everything the motor turns in this gear, referred to the spindle (additive key).
    # None: not known; speed changes then read as load (safe side, said at start).
    inertia_kgm2: float | None = Field(None, ge=0)


def _check_gears(gears: list[GearSettings]) -> list[GearSettings]:
    problems: list[tuple[str, str]] = []
    seen: dict[str, int] = {}
    for i, gear in enumerate(gears):
        if gear.name in seen:
            problems.append((f"[{i}].name", f"{json.dumps(gear.name)} is already the name of gears[{seen[gear.name]}] (unique gear names)"))
        seen.setdefault(gear.name, i)
        if i and gear.max_spindle_rpm <= gears[i - 1].max_spindle_rpm:
            problems.append(
                (
                    f"[{i}].max_spindle_rpm",
                    f"{gear.max_spindle_rpm:g} is not above the previous gear's {gears[i - 1].max_spindle_rpm:g} "
                    "(strictly increasing: list gears lowest max_spindle_rpm first)",
                )
            )
    if problems:
        raise problems_error(problems)
    return gears


GearList = Annotated[list[GearSettings], Field(min_length=1), AfterValidator(_check_gears)]


# --------------------------------------------------------------------------- [tool], [material], [cut], [depth]
def _cf_value(value: Any) -> Any:
    lo, hi = CF_RANGE
    expected = f'a number from {lo} to {hi}, "model" or "auto"'
    if value in ("model", "auto") and isinstance(value, str):
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{json.dumps(value) if isinstance(value, str) else type(value).__name__} is neither a number nor \"model\" ({expected})")
    if not lo <= float(value) <= hi:
        raise ValueError(f"{value!r} is outside {lo}–{hi} ({expected}; [P] measured 1.03–1.11)")
    return float(value)


class ToolSettings(_Section):
    """`[tool]`: the end mill. `cf` is C_f of [P] eq. (18) (a fitted number), "model" (the engaged teeth's
    forces added as vectors with r_1(t_a)), or "auto" (the default, additive: "model" where the cut's
    engagement and chip are known, [P]'s 1.075 for what is not; docs/physics.md §5)."""

    diameter_mm: float = Field(gt=0)
    flutes: int = Field(ge=1)
    cf: Annotated[float | Literal["model", "auto"], BeforeValidator(_cf_value)] = "auto"
    helix_deg: float | None = Field(None, gt=0, lt=90)
    flute_length_mm: float | None = Field(None, gt=0)   # (additive) unset: 2 × diameter_mm (physics/validity.py)


class ToolTableSettings(_Section):
    """`[tools.<number>]` (additive): one tool of the magazine by its CNC number (T12 → `[tools.12]`).

    Force and depth use the tool the context says is in the spindle; a tool
    not listed here uses `[tool]`. `cf` and `helix_deg` left out take `[tool]`'s.
    """

    diameter_mm: float = Field(gt=0)
    flutes: int = Field(ge=1)
    cf: Annotated[float | Literal["model", "auto"] | None,
                  BeforeValidator(lambda v: v if v is None else _cf_value(v))] = None
    helix_deg: float | None = Field(None, gt=0, lt=90)
    flute_length_mm: float | None = Field(None, gt=0)   # (additive) unset: 2 × this tool's diameter_mm


def _tool_number(value: Any) -> Any:
    """A `[tools.N]` table name: the CNC's tool number, 0 … 2³²−1 (daq-protocol.md: uint32)."""
    text = str(value)
    if not text.isdigit() or int(text) > 0xFFFFFFFF:
        raise ValueError(f"{text!r} is not a tool number (a whole number 0 … 4294967295, as [tools.12])")
    return int(text)


ToolNumber = Annotated[int, BeforeValidator(_tool_number)]


class MaterialSettings(_Section):
    """`[material]`: [D] eqs. (8)–(9) power laws, t_a in mm, K_s in N/mm². Defaults: [D] Table 2 (SB40)."""

    ks: float = Field(646.08, gt=0)
    ks_exp: float = -0.4362
    r1: float = Field(0.2201, gt=0)
    r1_exp: float = -0.2667
    r2: float = Field(0.1244, ge=0)
    r2_exp: float = 0.1702
    # the edge (ploughing) force per mm of engaged edge, N/mm (physics/edge.py; docs/physics.md §5b; additive):
    # 0, the law taken as all chip, as before
    edge_t_n_mm: float = Field(0.0, ge=0, le=1000)
    edge_r_n_mm: float = Field(0.0, ge=0, le=1000)


class CutSettings(_Section):
    """`[cut]`: milling mode, programmed feed, and a known depth if there is one."""

    mode: Literal["down", "up", "slot"] = "slot"
    feed_mm_min: float | None = Field(None, gt=0)  # used when the DAQ has no feed_rate channel
    axial_depth_mm: float | None = Field(None, gt=0)
    radial_depth_mm: float | None = Field(None, gt=0)


class DepthSettings(_Section):
    """`[depth]`: how the depth of cut is found ([D] §3) and when a revolution is an air cut."""

    method: Literal["auto", "dynamometer", "feed-drive", "torque-only", "off"] = "auto"
    min_torque_nm: float = Field(0.5, ge=0)


class FeedForceSettings(_Section):
    """`[feed_force] CHANNEL = {...}`: force_feed_n = newton_per_amp · current_a − friction_n."""

    newton_per_amp: float = Field(gt=0)
    friction_n: float = Field(0.0, ge=0)


# --------------------------------------------------------------------------- [alarms], [interlock]
_PAIRS = (("torque_warn_nm", "torque_limit_nm"), ("force_warn_n", "force_limit_n"), ("power_warn_w", "power_limit_w"))


class AlarmSettings(_Section):
    """`[alarms]`: every limit is optional; one left out is not armed.

    Additive keys (not in the first interfaces.md example):

    - `hysteresis_pct` (default 10): a level is left only below
      `limit · (1 − hysteresis_pct/100)`, so a cut hovering at a limit does not chatter;
    - `breakage_drop_pct` (default: not armed): a drop of the revolution torque
      from one steady level to another this large, within one revolution, at
      constant speed and feed, is a `tool_breakage` (pipeline/alarms.py
      `BreakageTrack`). A 2-flute cutter that loses a flute drops about 25 %, a
      4-flute one about 12 %: set it below that;
    - `breakage_min_torque_nm` (default 1.0): breakage is only judged after
      steady revolutions cutting with at least this torque;
    - `crash_current_a` (sample level, like `crash_power_w`): the smoothed
      largest line current over this trips at once. A clipped current sample
      counts as over it;
    - `stall_current_a`: a spindle that stops under load closes no revolution and
      its power falls with speed: while the line current stays above this, no
      revolution closing within twice the last revolution's period trips.
    """

    torque_warn_nm: float | None = Field(None, gt=0)
    torque_limit_nm: float | None = Field(None, gt=0)
    force_warn_n: float | None = Field(None, gt=0)
    force_limit_n: float | None = Field(None, gt=0)
    power_warn_w: float | None = Field(None, gt=0)
    power_limit_w: float | None = Field(None, gt=0)
    revolutions: int = Field(2, ge=1)
    crash_power_w: float | None = Field(None, gt=0)
    hysteresis_pct: float = Field(10.0, ge=0, lt=100)
    breakage_drop_pct: float | None = Field(None, ge=0, lt=100)  # 0: off, as before (kept for old files)
    breakage_min_torque_nm: float = Field(1.0, ge=0)
    crash_current_a: float | None = Field(None, gt=0)
    stall_current_a: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _warn_below_limit(self) -> AlarmSettings:
        if self.breakage_drop_pct == 0:
            self.breakage_drop_pct = None  # "0 = off" of the first contract: the same as left out
        problems = []
        for warn, limit in _PAIRS:
            w, lim = getattr(self, warn), getattr(self, limit)
            if w is not None and lim is not None and w >= lim:
                problems.append((warn, f"{w:g} is not below {limit} = {lim:g} (a warning level under the limit)"))
        if problems:
            raise problems_error(problems)
        return self


MIN_TOKEN_CHARS = 32  # 128 bits as hex; `millsense token new` prints 43 base64url characters (256 bits)


class InterlockSettings(_Section):
    """`[interlock]`: feed hold on overload, DAQ watchdog fed by heartbeats.

    Security keys (additive): `reset` says who may send commands (`cmd/*`) over
    Zenoh: "token" (the requester proves it knows `reset_token`, or the content
    of `reset_token_file`, by a challenge–response: the token never crosses the
    network; it is kept out of logs, `repr` and the `config` queryable), "open"
    (anyone who reaches the queryable), or "off" (none; the local reset at the
    machine still works). Left out, it is "token" whenever the daemon's Zenoh
    session may be reached from off the host, else "open" (config.py resolves
    it). A token given with a policy other than "token" is refused: it would
    protect nothing.

    `on_blind` (additive): what the interlock does when the daemon cannot see
    (implausible signals, a DAQ that does not fit the config) while the spindle
    turns: "hold" (default) latches feed hold, "alarm" only reports it.
    """

    enabled: bool = False
    heartbeat_ms: int = Field(100, ge=10, le=60000)
    watchdog_ms: int = Field(500, ge=10, le=600000)
    reset: Literal["open", "token", "off"] | None = None
    reset_token: SecretStr | None = None
    reset_token_file: str | None = None
    on_blind: Literal["hold", "alarm"] = "hold"

    @model_validator(mode="after")
    def _consistent(self) -> InterlockSettings:
        problems = []
        if self.watchdog_ms <= self.heartbeat_ms:
            problems.append(
                ("watchdog_ms", f"{self.watchdog_ms} is not above heartbeat_ms = {self.heartbeat_ms} (a watchdog longer than the heartbeat period, e.g. 5×)")
            )
        token = self.reset_token.get_secret_value() if self.reset_token is not None else ""
        if token and self.reset_token_file:
            problems.append(("reset_token", "given together with reset_token_file (one of the two)"))
        if self.reset in ("open", "off"):
            for key in ("reset_token", "reset_token_file"):
                if getattr(self, key):
                    problems.append((key, f'set but reset = "{self.reset}" ignores it (reset = "token" to require it)'))
        elif self.reset == "token" and not token and not self.reset_token_file:
            problems.append(("reset_token", 'missing: reset = "token" needs a secret (reset_token_file, made by `millsense token new`)'))
        if token and len(token) < MIN_TOKEN_CHARS:
            problems.append(("reset_token", f"{len(token)} characters is too short to resist guessing (at least "
                                            f"{MIN_TOKEN_CHARS}: `millsense token new` makes one)"))
        if problems:
            raise problems_error(problems)
        return self

    def token(self) -> str:
        """The reset secret as plain text ("" if none); the only way to read it."""
        return self.reset_token.get_secret_value() if self.reset_token is not None else ""


# --------------------------------------------------------------------------- [zenoh], [log]
def endpoint_problem(endpoint: str) -> str | None:
    """Why `endpoint` is not a Zenoh endpoint like `tcp/10.0.0.5:7447`, or None if it is."""
    m = _ENDPOINT_RE.match(endpoint)
    expected = "like tcp/10.0.0.5:7447, udp/…, tls/host:7447, quic/…, ws/…, unixsock-stream/PATH"
    shown = json.dumps(endpoint)
    if not m:
        return f"{shown} is not an endpoint ({expected})"
    proto, addr = m.group("proto"), m.group("addr")
    if proto == "unixsock-stream":
        return None if addr else f"{shown} has no socket path ({expected})"
    if proto not in _IP_PROTOCOLS:
        return f"{shown}: unknown protocol {json.dumps(proto)} ({expected})"
    hp = _HOST_PORT_RE.match(addr)
    if not hp:
        return f"{shown}: {json.dumps(addr)} is not host:port ({expected}; IPv6 in brackets)"
    if int(hp.group("port")) > 65535:
        return f"{shown}: port {hp.group('port')} is above 65535 ({expected})"
    return None


def is_loopback_endpoint(endpoint: str) -> bool:
    """Can only this host reach `endpoint`? (a Unix socket, 127.0.0.0/8, ::1, localhost)"""
    m = _ENDPOINT_RE.match(endpoint)
    if not m:
        return False
    if m.group("proto") == "unixsock-stream":
        return True
    hp = _HOST_PORT_RE.match(m.group("addr"))
    if not hp:
        return False
    host = hp.group("host").strip("[]").lower()
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def loopback_only(zenoh: Any) -> bool:
    """Does this `[zenoh]` section keep the session's queryables away from other hosts?

    Only a peer that listens on loopback endpoints alone and connects to none.
    A peer with no `listen` takes Zenoh's default, every interface; anything it
    connects to, even on 127.0.0.1, may be a router that relays other hosts'
    queries (so is a client's router); a JSON5 `config_file` may add endpoints
    this check cannot see. None of those counts.
    """
    if zenoh.config_file or zenoh.mode != "peer" or zenoh.connect or not zenoh.listen:
        return False
    return all(is_loopback_endpoint(e) for e in zenoh.listen)


def _check_endpoints(endpoints: list[str]) -> list[str]:
    problems = [(f"[{i}]", p) for i, e in enumerate(endpoints) if (p := endpoint_problem(e))]
    if problems:
        raise problems_error(problems)
    return endpoints


Endpoints = Annotated[list[str], AfterValidator(_check_endpoints)]


class ZenohSettings(_Section):
    """`[zenoh]`: session mode and endpoints; `config_file` is a Zenoh JSON5 (TLS, auth, ACL)
    merged under these keys. `multicast_scouting` (additive, default true) — tests and
    TLS deployments turn it off and give explicit endpoints."""

    mode: Literal["peer", "client"] = "peer"
    connect: Endpoints = Field(default_factory=list)
    listen: Endpoints = Field(default_factory=list)
    multicast_scouting: bool = True
    config_file: str = ""
    # Zenoh shared memory (additive, default off): a local peer could make the daemon map
    # 16 MB segments that are never given back.
    shared_memory: bool = False


class SignalSettings(_Section):
    """`[signals]` (additive section): plausibility of the DAQ's signals while the spindle turns.

    A revolution with a clipped, flat or dead channel, or whose spindle speed
    disagrees with the electrical frequency or the encoder by more than
    `speed_tolerance_pct`, is published `valid: false`, and fault `signals`
    names the channel (pipeline/signal_check.py).
    """

    speed_tolerance_pct: float = Field(10.0, gt=0, le=100)


class ContextSettings(_Section):
    """`[context]` (additive): where the daemon learns what the machine is doing.

    "auto": the DAQ's CONTEXT frames when its descriptor says it reports
    context (protocol 2, capabilities bit 1), else the Zenoh key
    `millsense/<machine>/context` (a CNC adapter puts it); "daq" or "zenoh":
    only that one; "off": none, so no learned limits, only the fixed ones.

    Authority (issue 36, additive; docs/security.md, "Who may publish context"):
    any Zenoh put labels the cut, but adaptive feed control follows a Zenoh
    context only when it is signed with `adapter_key` (or the content of
    `adapter_key_file`, made by `millsense token new`, never the reset token)
    or when `trust = "acl"` says the router lets only CNC adapters put it.
    Default `trust = "none"`: nobody is trusted for it.
    """

    source: Literal["auto", "daq", "zenoh", "off"] = "auto"
    trust: Literal["none", "acl"] = "none"
    adapter_key: SecretStr | None = None
    adapter_key_file: str | None = None

    @model_validator(mode="after")
    def _consistent(self) -> ContextSettings:
        problems = []
        key = self.adapter_key.get_secret_value() if self.adapter_key is not None else ""
        if key and self.adapter_key_file:
            problems.append(("adapter_key", "given together with adapter_key_file (one of the two)"))
        if key and len(key) < MIN_TOKEN_CHARS:
            problems.append(("adapter_key", f"{len(key)} characters is too short to resist guessing (at least "
                                            f"{MIN_TOKEN_CHARS}: `millsense token new` makes one)"))
        if self.adapter_key is not None and not key:
            problems.append(("adapter_key", "empty (a secret of at least 32 characters from `millsense token new`)"))
        if problems:
            raise problems_error(problems)
        return self

    def key(self) -> str:
        """The adapter key as plain text ("" if none); the only way to read it."""
        return self.adapter_key.get_secret_value() if self.adapter_key is not None else ""


class LearningSettings(_Section):
    """`[learning]` (additive): limits learned per process (program, tool, operation).

    The first `processes` processes of a key that raised no alarm teach its
    envelope: per revolution from entry, the learned mean ± max(`sigma` standard
    deviations, `min_width_pct` % of the mean, `min_width_nm` / `min_width_n`).
    The fixed `[alarms]` limits stay armed throughout. See docs/learning.md.
    """

    enabled: bool = True
    processes: int = Field(5, ge=2, le=100)
    confirm: bool = False
    sigma: float = Field(4.0, gt=0, le=20)
    min_width_pct: float = Field(25.0, ge=0, le=200)
    # the low side's floor: a broken flute drops the torque by only 15–25 %, so the band below the
    # mean is narrower than above it (where it must stay wider than wear_rise_pct); None: half of min_width_pct
    min_width_low_pct: float | None = Field(None, ge=0, le=200)
    min_width_nm: float = Field(0.5, ge=0)
    min_width_n: float = Field(50.0, ge=0)
    high_revolutions: int = Field(3, ge=1, le=1000)
    low_revolutions: int = Field(3, ge=1, le=1000)
    hold_high: bool = True
    hold_low: bool = True
    wear_rise_pct: float = Field(15.0, gt=0, le=500)
    wear_window: int = Field(3, ge=1, le=100)
    # (issue 41, additive) the expected band around the physics' load of an `[operations]` entry, ± this %;
    # the default from the measured spread: 30 first parts, material batches ±20 %, tools at 80 % life
    # (docs/validation.md, "The expected load of a first part")
    physics_tolerance_pct: float = Field(34.0, gt=0, le=200)
    # (issue 41, additive) a TOML file of `[operations.*]` tables only, written by `millsense limits
    # import-operations`; relative to the config file's folder. "" = none
    operations_file: str = ""


class HistorySettings(_Section):
    """`[history]` (additive): the embedded SQLite history in the state directory.

    Learned limits, process summaries, alarms and (with `revolutions`) every
    per-revolution estimate; kept `retention_days` and at most `max_mb`
    (the oldest revolutions go first). See docs/history.md.
    """

    enabled: bool = True
    path: str = ""
    retention_days: float = Field(30.0, gt=0, le=3650)
    max_mb: float = Field(500.0, ge=1, le=1_000_000)
    revolutions: bool = True


class LogSettings(_Section):
    """`[log]`: level, and format "auto" (console on a TTY, JSON otherwise), "json" or "console"."""

    level: Literal["debug", "info", "warning", "error", "critical"] = "info"
    format: Literal["auto", "json", "console"] = "auto"


# --------------------------------------------------------------------------- [operations.*], [materials.*]
MATERIAL_NAME_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"


def _operation_key(value: Any) -> Any:
    """An `[operations."P/T/O"]` name: the learned limits' key, program/tool/operation as the CNC reports them."""
    text = str(value)
    parts = text.split("/")
    if (len(parts) != 3 or not all(p.isascii() and p.isdigit() and len(p) <= 10 for p in parts)
            or int(parts[0]) > 0xFFFFFFFF or int(parts[1]) > 0xFFFFFFFF or int(parts[2]) > 0xFFFF):
        raise ValueError(f"{text!r} is not PROGRAM/TOOL/OPERATION (program and tool 0 … 4294967295, operation "
                         f"0 … 65535, as \"1234/12/3\")")
    return "/".join(str(int(p)) for p in parts)


OperationKey = Annotated[str, BeforeValidator(_operation_key)]
MaterialName = Annotated[str, Field(pattern=MATERIAL_NAME_PATTERN)]


class OperationSettings(_Section):
    """`[operations."PROGRAM/TOOL/OPERATION"]` (issue 41, additive): one operation's programmed cut.

    The physics' expected load of its steady revolutions guards it from the first part (docs/learning.md).
    `ae_mm` / `ap_mm` are the maximum depths; exactly one of `fz_mm` (per tooth, G95-like) and
    `vf_mm_min` (feed rate, G94-like). With `mode = "slot"` the radial depth is the tool's diameter:
    `ae_mm` may be left out, and if given must equal it (checked against the tool). `material` names a
    `[materials.NAME]` section; left out, `[material]`. `spindle_rpm` (optional): the programmed speed,
    for `limits show` before a revolution was seen.
    """

    ae_mm: float | None = Field(None, gt=0)
    ap_mm: float = Field(gt=0)
    fz_mm: float | None = Field(None, gt=0)
    vf_mm_min: float | None = Field(None, gt=0)
    mode: Literal["slot", "up", "down"]
    engagement: Literal["constant", "varying"]
    material: str | None = Field(None, pattern=MATERIAL_NAME_PATTERN)
    spindle_rpm: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _one_feed(self) -> OperationSettings:
        problems = []
        if (self.fz_mm is None) == (self.vf_mm_min is None):
            problems.append(("fz_mm", "give exactly one of fz_mm (feed per tooth, mm) and vf_mm_min (feed rate, "
                                      f"mm/min), not {'both' if self.fz_mm is not None else 'neither'}"))
        if self.ae_mm is None and self.mode != "slot":
            problems.append(("ae_mm", f'missing (mode = "{self.mode}" needs the maximum radial depth, mm; only a '
                                      'slot takes the tool\'s diameter)'))
        if problems:
            raise problems_error(problems)
        return self


# --------------------------------------------------------------------------- [afc]
AFC_MIN_GAIN = 0.1  # d ln(load) / d ln(feed) below it: the load barely follows the feed, the loop gain explodes
AFC_QUANTITIES = {"torque": "torque_nm", "force": "force_n", "power": "power_w"}  # quantity -> its target key


def _afc_target_key(value: Any) -> Any:
    """An `[afc.targets."T/O"]` name: tool number / operation number, or "T/*" for any operation of tool T."""
    text = str(value)
    tool, sep, op = text.partition("/")
    expected = 'as "12/3" (tool 12, operation 3) or "12/*" (any operation of tool 12)'
    if (not sep or not tool.isdigit() or int(tool) > 0xFFFFFFFF
            or not (op == "*" or (op.isdigit() and int(op) <= 0xFFFF))):
        raise ValueError(f"{text!r} is not TOOL/OPERATION (tool 0 … 4294967295, operation 0 … 65535 or *; {expected})")
    return f"{int(tool)}/{op if op == '*' else int(op)}"


AfcTargetKey = Annotated[str, BeforeValidator(_afc_target_key)]


class AfcTargetSettings(_Section):
    """`[afc.targets."T/O"]`: one tool's (and operation's) target, and whether AFC may run there."""

    torque_nm: float | None = Field(None, gt=0)
    force_n: float | None = Field(None, gt=0)
    power_w: float | None = Field(None, gt=0)
    allow: bool | None = None  # true: without the CONTEXT flag too; false: never (tapping, thread milling)


class AfcSettings(_Section):
    """`[afc]` (additive): adaptive feed control through the CNC's feed override (docs/afc.md).

    The controller holds `quantity` at a target by moving the override within
    `min_override_pct` … `max_override_pct`. `enabled` switches it on at start
    (default off); `cmd/afc` switches it on and off while running, not persisted.
    """

    enabled: bool = False
    quantity: Literal["torque", "force", "power"] = "torque"
    min_override_pct: float = Field(50.0, gt=0, lt=100)
    max_override_pct: float = Field(150.0, ge=100, le=200)
    air_override_pct: float = Field(100.0, gt=0, le=200)
    arm_pct: float = Field(30.0, ge=0, lt=100)
    target_factor: float = Field(1.0, gt=0, le=10)
    rate_pct_s: float = Field(600.0, gt=0, le=10000)
    cnc_lag_ms: float = Field(40.0, ge=0, le=10000)
    closed_loop_s: float = Field(0.0, ge=0, le=600)
    process_gain: float = Field(0.0, ge=0, le=5)
    allow: bool = False
    target_torque_nm: float | None = Field(None, gt=0)
    target_force_n: float | None = Field(None, gt=0)
    target_power_w: float | None = Field(None, gt=0)
    targets: dict[AfcTargetKey, AfcTargetSettings] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _consistent(self) -> AfcSettings:
        problems = []
        if not self.min_override_pct <= self.air_override_pct <= self.max_override_pct:
            problems.append(("air_override_pct", f"{self.air_override_pct:g} is outside min_override_pct … "
                                                 f"max_override_pct = {self.min_override_pct:g} … {self.max_override_pct:g} "
                                                 "(within the bounds, 100 or below recommended)"))
        if problems:
            raise problems_error(problems)
        return self

    def target_key(self) -> str:
        """The key of `quantity` in a `[afc.targets]` entry (torque_nm, force_n, power_w)."""
        return AFC_QUANTITIES[self.quantity]


# --------------------------------------------------------------------------- [opcua] (issue 42)
# Its own module (the OPC UA server's keys); imported here, after _Section, for the file's model below.
from millsense.daemon.config.opcua_section import OpcuaSettings  # noqa: E402


# --------------------------------------------------------------------------- the file
class Settings(_Section):
    """The whole configuration file. Required: machine, [daq], [channels.*], [motor], [[gears]], [tool]."""

    machine: str = Field(pattern=MACHINE_PATTERN, max_length=64)
    calibration: str = ""
    daq: DaqSettings
    channels: dict[ChannelName, ChannelSettings] = Field(min_length=1)
    motor: MotorSettings
    gears: GearList
    tool: ToolSettings
    tools: dict[ToolNumber, ToolTableSettings] = Field(default_factory=dict)
    material: MaterialSettings = Field(default_factory=MaterialSettings)
    materials: dict[MaterialName, MaterialSettings] = Field(default_factory=dict)   # (issue 41, additive)
    operations: dict[OperationKey, OperationSettings] = Field(default_factory=dict)   # (issue 41, additive)
    cut: CutSettings = Field(default_factory=CutSettings)
    depth: DepthSettings = Field(default_factory=DepthSettings)
    feed_force: dict[ChannelName, FeedForceSettings] = Field(default_factory=dict)
    alarms: AlarmSettings = Field(default_factory=AlarmSettings)
    interlock: InterlockSettings = Field(default_factory=InterlockSettings)
    signals: SignalSettings = Field(default_factory=SignalSettings)
    context: ContextSettings = Field(default_factory=ContextSettings)
    learning: LearningSettings = Field(default_factory=LearningSettings)
    history: HistorySettings = Field(default_factory=HistorySettings)
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    log: LogSettings = Field(default_factory=LogSettings)
    afc: AfcSettings = Field(default_factory=AfcSettings)
    opcua: OpcuaSettings = Field(default_factory=OpcuaSettings)   # (issue 42, additive) read by `millsense opcua`
