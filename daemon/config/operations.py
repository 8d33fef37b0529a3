"""`[operations.*]` and `[materials.*]` (issue 41): the checks across sections, the operations file, the CSV sheet.

An operation's fields are checked in `models.OperationSettings`; here what needs another section: its tool
(`[tools.N]` with N the key's TOOL, else `[tool]`), its material (`[materials.NAME]`), and the file of
`[operations.*]` tables that `millsense limits import-operations` writes (`[learning] operations_file`).
Every problem names its section and key, as check-config does (exit 78).

`operation_cut` turns one operation into what the forward physics takes (`physics.expected.ProgrammedCut`,
the tool's radius and flutes, the `Material`).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

from pydantic import ValidationError

from millsense.daemon.physics.validity import default_flute_length_mm

# The CSV sheet's header, exactly (units in the names). Empty cells: not given.
CSV_COLUMNS = ("program", "tool", "operation", "ae_mm", "ap_mm", "fz_mm", "vf_mm_min", "mode", "engagement",
               "material", "spindle_rpm")
OPERATIONS_HEADER = ("# [operations.*] written by `millsense limits import-operations` (docs/learning.md).\n"
                     "# Rewritten on each import: keep hand edits in the main configuration's [operations].\n")


def _iso_group(name: str, settings: Any) -> Any:
    """An ISO material group's letter (P, M, K, N, S): its handbook law (physics/materials.py, docs/physics.md §5a)."""
    from millsense.daemon.physics.materials import ISO_GROUPS

    group = ISO_GROUPS.get(name)
    return None if group is None else group.material


# Where a material name is looked up after `[materials.NAME]` (which comes first, so a plant's own
# measured "P" wins over the handbook's): (name, settings) -> a MaterialSettings-like object or None.
MATERIAL_LOOKUPS: list[Callable[[str, Any], Any]] = [_iso_group]


class OperationCut(NamedTuple):
    """An operation ready for `physics.expected.expected_load`."""

    key: str
    cut: Any                 # ProgrammedCut
    tool_radius_mm: float
    flutes: int
    material: Any            # physics.milling.Material
    engagement: str          # "constant" | "varying"
    spindle_rpm: float | None
    helix_deg: float | None = None   # the tool's; None counts the flutes straight (the larger force)


def _loc(key: str) -> str:
    return f'operations."{key}"'


def tool_for(tool_number: int, tool: Any, tools: Mapping[int, Any] | None) -> Any:
    """The tool an operation cuts with: `[tools.N]`, else `[tool]` (as force and depth take it)."""
    return (tools or {}).get(tool_number) or tool


def material_for(name: str | None, material: Any, materials: Mapping[str, Any] | None, settings: Any = None) -> Any:
    """`[material]` for None; `[materials.NAME]`; then each of MATERIAL_LOOKUPS; None when unknown."""
    if name is None:
        return material
    found = (materials or {}).get(name)
    for lookup in MATERIAL_LOOKUPS:
        if found is not None:
            break
        found = lookup(name, settings)
    return found


def operation_problems(parts: Mapping[str, Any]) -> list[str]:
    """Each operation against its tool and material (skipped where that section is itself invalid)."""
    ops, tool, tools = parts.get("operations"), parts.get("tool"), parts.get("tools")
    if not ops or tool is None or tools is None:
        return []
    materials = parts.get("materials")
    problems: list[str] = []
    for key, op in sorted(ops.items()):
        t = tool_for(int(key.split("/")[1]), tool, tools)
        d = float(t.diameter_mm)
        where = "tools." + key.split("/")[1] if int(key.split("/")[1]) in tools else "tool"
        if op.ae_mm is not None:
            if op.mode == "slot" and not math.isclose(op.ae_mm, d, rel_tol=1e-9):
                problems.append(f'{_loc(key)}.ae_mm: {op.ae_mm:g} with mode = "slot" is not {where}.diameter_mm '
                                f"= {d:g} (a slot cuts the whole diameter: leave ae_mm out, or give up/down)")
            elif op.ae_mm > d:
                problems.append(f"{_loc(key)}.ae_mm: {op.ae_mm:g} is above {where}.diameter_mm = {d:g} "
                                "(a radial depth within (0, diameter])")
        flute = t.flute_length_mm if t.flute_length_mm is not None else default_flute_length_mm(d)
        if op.ap_mm > flute:
            given = "flute_length_mm" if t.flute_length_mm is not None else "flute_length_mm (unset: 2 × diameter_mm)"
            problems.append(f"{_loc(key)}.ap_mm: {op.ap_mm:g} is above {where}.{given} = {flute:g} "
                            "(an axial depth the flutes can cut)")
        if op.material is not None and materials is not None and material_for(op.material, None, materials) is None:
            from millsense.daemon.physics.materials import ISO_GROUPS

            known = ", ".join(sorted(materials)) or "none"
            problems.append(f"{_loc(key)}.material: {json.dumps(op.material)} is no [materials.NAME] section "
                            f"(known: {known}) and no ISO group ({', '.join(ISO_GROUPS)})")
    return problems


def operation_cut(settings: Any, key: str) -> OperationCut | None:
    """The operation of `key` as the physics takes it; None when the key has none (behaves as before)."""
    from millsense.daemon.physics.expected import ProgrammedCut
    from millsense.daemon.physics.milling import Material

    op = (getattr(settings, "operations", None) or {}).get(key)
    if op is None:
        return None
    tool = tool_for(int(key.split("/")[1]), settings.tool, getattr(settings, "tools", None))
    m = material_for(op.material, settings.material, getattr(settings, "materials", None), settings)
    if m is None:
        return None   # refused at load; never a guess
    d = float(tool.diameter_mm)
    cut = ProgrammedCut(radial_depth_mm=d if op.mode == "slot" else float(op.ae_mm), axial_depth_mm=float(op.ap_mm),
                        mode=op.mode, feed_per_tooth_mm=op.fz_mm, feed_mm_min=op.vf_mm_min)
    material = Material(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp, float(getattr(m, "edge_t_n_mm", 0.0)),
                        float(getattr(m, "edge_r_n_mm", 0.0)))
    return OperationCut(key, cut, d / 2.0, int(tool.flutes), material, op.engagement, op.spindle_rpm,
                        getattr(tool, "helix_deg", None))


def operation_cuts(settings: Any) -> dict[str, OperationCut]:
    """Every operation of `settings` as the physics takes it (learning/expected.py's `ExpectedBand`)."""
    out = {}
    for key in getattr(settings, "operations", None) or {}:
        cut = operation_cut(settings, key)
        if cut is not None:
            out[key] = cut
    return out


# ----------------------------------------------------------------------------- the operations file
def include_operations_file(data: dict[str, Any], base_dir: Path) -> list[str]:
    """Merge `[learning] operations_file`'s `[operations.*]` into `data` (before validation); its problems.

    The file holds `[operations.*]` tables and nothing else. A key in both it and the main configuration
    is refused (which one would hold is not for the daemon to guess).
    """
    learning = data.get("learning")
    name = learning.get("operations_file") if isinstance(learning, dict) else None
    if not isinstance(name, str) or not name:
        return []
    from millsense.daemon.config.checks import read_toml

    path = Path(name).expanduser()
    path = path if path.is_absolute() else base_dir / path
    what = "a TOML file of [operations.*] tables, written by `millsense limits import-operations`"
    loaded, problems = read_toml(path, f"learning.operations_file: {path}", what)
    if loaded is None:
        return problems
    extra = sorted(k for k in loaded if k != "operations")
    if extra:
        return [f"learning.operations_file: {path} has {', '.join(extra)} ({what})"]
    ops = loaded.get("operations", {})
    if not isinstance(ops, dict):
        return [f"learning.operations_file: {path}: operations is not a table ({what})"]
    mine = data.setdefault("operations", {})
    if not isinstance(mine, dict):
        return []   # the main file's own problem, reported by its validation
    both = sorted(set(mine) & set(ops))
    if both:
        return [f'{_loc(both[0])}: in both the configuration and learning.operations_file {path} (one place: '
                f"remove it from one of them)"]
    mine.update(ops)
    return []


# ----------------------------------------------------------------------------- the CSV sheet
def read_operations_csv(text: str, source: str,
                        row_of: dict[str, int] | None = None) -> tuple[dict[str, dict[str, Any]], list[str]]:
    """A CSV sheet of operations → ({key: fields}, problems), each problem naming its row and section.key;
    `row_of` (if given) gets each key's row number (the header is row 1)."""
    from millsense.daemon.config.errors import problems_from
    from millsense.daemon.config.models import OperationSettings, Settings, _operation_key

    rows = list(csv.reader(io.StringIO(text)))
    if not rows:
        return {}, [f"{source}: empty (a header line {','.join(CSV_COLUMNS)})"]
    header = [h.strip() for h in rows[0]]
    if header and header[0].startswith("\ufeff"):
        header[0] = header[0][1:]
    if tuple(header) != CSV_COLUMNS:
        return {}, [f"{source}: row 1: the header is {','.join(header)}; expected exactly {','.join(CSV_COLUMNS)}"]
    out: dict[str, dict[str, Any]] = {}
    problems: list[str] = []
    for number, row in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in row):
            continue
        if len(row) != len(CSV_COLUMNS):
            problems.append(f"{source}: row {number}: {len(row)} cells, expected {len(CSV_COLUMNS)}")
            continue
        cells = dict(zip(CSV_COLUMNS, (c.strip() for c in row)))
        key_text = f"{cells['program']}/{cells['tool']}/{cells['operation']}"
        fields: dict[str, Any] = {}
        bad = False
        for name in CSV_COLUMNS[3:]:
            value = cells[name]
            if value == "":
                continue
            if name in ("mode", "engagement", "material"):
                fields[name] = value
                continue
            try:
                number_value = float(value)
            except ValueError:
                problems.append(f'{source}: row {number}: {_loc(key_text)}.{name}: {json.dumps(value)} is not a number')
                bad = True
                continue
            fields[name] = number_value
        if bad:
            continue
        try:
            key = _operation_key(key_text)
        except ValueError as exc:
            problems.append(f"{source}: row {number}: operations: {exc}")
            continue
        if key in out:
            problems.append(f"{source}: row {number}: {_loc(key)}: given twice (one row per operation)")
            continue
        try:
            OperationSettings.model_validate(fields)
        except ValidationError as exc:
            problems.extend(f"{source}: row {number}: {p}"
                            for p in problems_from(Settings, exc, prefix=("operations", key)))
            continue
        out[key] = fields
        if row_of is not None:
            row_of[key] = number
    return out, problems


def toml_value(value: Any) -> str:
    if isinstance(value, str):
        return json.dumps(value)   # a TOML basic string: JSON's escapes are TOML's
    return repr(float(value)) if isinstance(value, float) else str(value)


def operations_toml(ops: Mapping[str, Mapping[str, Any]]) -> str:
    """`[operations."KEY"]` tables, keys sorted by program, tool, operation."""
    lines = [OPERATIONS_HEADER]
    for key in sorted(ops, key=lambda k: tuple(int(p) for p in k.split("/"))):
        lines.append(f'[operations."{key}"]')
        lines += [f"{name} = {toml_value(v)}" for name, v in ops[key].items() if v is not None]
        lines.append("")
    return "\n".join(lines)


def write_atomically(path: Path, text: str) -> None:
    """Replace `path` in one step (a reader sees the old file or the new one, never half)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=str(path.parent))
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
