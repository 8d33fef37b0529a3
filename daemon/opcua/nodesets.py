"""The OPC Foundation's companion-specification nodesets, imported into the asyncua server (issue 42).

`millsense opcua --nodesets DIR` (or `[opcua] nodesets_dir`) names a folder holding the NodeSet2 XML
files of DI, IA, Machinery, ISA-95 Job Control, Machinery Jobs and MachineTool (OPC 40501). They are
not restated here: the folder is read, each file's `<Models>` says which model it is and which it
requires, and they are imported in that dependency order, whatever the files are called.

asyncua 2.1.0 does not import them as the OPC Foundation ships them (measured with
node-opcua-nodesets 2.185.0; docs/opcua.md):

- DI declares objects with `DesignToolOnly="true"` and no parent (templates for modelling tools).
  asyncua adds them anyway and fails with BadParentNodeIdInvalid. The UANodeSet schema says such
  nodes are for design tools, not for a server's address space: they are left out.
- Machinery Jobs declares an OptionSet structure, and asyncua's on-the-fly data-type code generation
  (`auto_load_definitions`) fails on it ("Unknown datatype ... OutputInformationDataType"): every file
  is imported with it off, and the data types are loaded once, after the last file
  (`load_data_type_definitions`).

A folder that cannot be imported raises NodesetError naming the file and the node; the caller exits 78.
Never a silent fallback to millsense's own model: that is only what runs without a folder.
"""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import structlog

log = structlog.get_logger("millsense.opcua")

UA_NS = "http://opcfoundation.org/UA/"
DI_NS = "http://opcfoundation.org/UA/DI/"
IA_NS = "http://opcfoundation.org/UA/IA/"
MACHINERY_NS = "http://opcfoundation.org/UA/Machinery/"
JOBCONTROL_NS = "http://opcfoundation.org/UA/ISA95-JOBCONTROL_V2/"
MACHINERY_JOBS_NS = "http://opcfoundation.org/UA/Machinery/Jobs/"
MACHINE_TOOL_NS = "http://opcfoundation.org/UA/MachineTool/"
# The models millsense needs, by their model URI (what a file's <Models> declares), with a name for messages.
REQUIRED_MODELS = {DI_NS: "DI", IA_NS: "IA", MACHINERY_NS: "Machinery", JOBCONTROL_NS: "ISA-95 Job Control",
                   MACHINERY_JOBS_NS: "Machinery Jobs", MACHINE_TOOL_NS: "MachineTool (OPC 40501)"}
MAX_FILE_BYTES = 64 * 1024 * 1024  # the largest of the six is under 2 MB; a bigger file is not a nodeset of these
_UANODESET = "{http://opcfoundation.org/UA/2011/03/UANodeSet.xsd}"


class NodesetError(Exception):
    """A nodeset folder that cannot be used; the message names the file and, where one is to blame, the node."""


@dataclass
class Nodeset:
    path: Path
    model_uri: str
    version: str
    publication_date: str
    requires: list[str]
    design_tool_only: set[str]  # NodeIds (as written in the file) the import leaves out

    @property
    def name(self) -> str:
        return REQUIRED_MODELS.get(self.model_uri, self.model_uri)


def read_header(path: Path) -> Nodeset | None:
    """The model a NodeSet2 file declares and what it requires; None for an XML file that declares none.

    Raises NodesetError for a file that is not XML."""
    try:
        if path.stat().st_size > MAX_FILE_BYTES:
            raise NodesetError(f"{path}: larger than {MAX_FILE_BYTES // 2**20} MB: not a NodeSet2 file of these")
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise NodesetError(f"{path}: cannot be read as XML: {exc}") from None
    if root.tag != f"{_UANODESET}UANodeSet":
        return None
    model = root.find(f"{_UANODESET}Models/{_UANODESET}Model")
    if model is None:
        return None
    requires = [r.get("ModelUri", "") for r in model.findall(f"{_UANODESET}RequiredModel")]
    skip = {el.get("NodeId", "") for el in root if el.get("DesignToolOnly", "").lower() == "true"}
    return Nodeset(path=path, model_uri=model.get("ModelUri", ""), version=model.get("Version", ""),
                   publication_date=model.get("PublicationDate", ""), requires=requires, design_tool_only=skip)


def find_nodesets(folder: Path) -> list[Nodeset]:
    """The six required models' files in `folder`, in dependency order. Raises NodesetError."""
    if not folder.is_dir():
        raise NodesetError(f"{folder}: not a directory (the folder of the NodeSet2 XML files; docs/opcua.md)")
    found: dict[str, Nodeset] = {}
    for path in sorted(folder.iterdir()):
        if path.suffix.lower() != ".xml" or not path.is_file():
            continue
        header = read_header(path)
        if header is None or header.model_uri not in REQUIRED_MODELS:
            continue  # another companion specification: not ours to import
        if header.model_uri in found:
            raise NodesetError(f"{path}: declares {header.model_uri} again (also {found[header.model_uri].path.name}): "
                               "keep one file per model")
        found[header.model_uri] = header
    missing = [f"{name} ({uri})" for uri, name in REQUIRED_MODELS.items() if uri not in found]
    if missing:
        raise NodesetError(f"{folder}: no NodeSet2 file for {', '.join(missing)}")
    ordered: list[Nodeset] = []

    def visit(uri: str, path: tuple[str, ...]) -> None:
        if uri == UA_NS or any(n.model_uri == uri for n in ordered):
            return
        if uri in path:
            raise NodesetError(f"{found[uri].path}: its required models form a cycle ({' -> '.join(path + (uri,))})")
        if uri not in found:
            raise NodesetError(f"{found[path[-1]].path}: requires the model {uri}, which no file in {folder} declares")
        for required in found[uri].requires:
            visit(required, path + (uri,))
        ordered.append(found[uri])

    for uri in REQUIRED_MODELS:
        visit(uri, ())
    return ordered


def _importer_class() -> Any:
    from asyncua.common.xmlimporter import XmlImporter

    class Importer(XmlImporter):
        """asyncua's importer, leaving out the DesignToolOnly nodes and naming the node an import fails on."""

        def __init__(self, server: Any, nodeset: Nodeset) -> None:
            super().__init__(server, strict_mode=True, auto_load_definitions=False)
            self.nodeset = nodeset

        def make_objects(self, node_data: list[Any]) -> list[Any]:
            kept = [n for n in node_data if n.nodeid not in self.nodeset.design_tool_only]
            # as the file writes them (asyncua renumbers the namespaces): what an error message names
            self.written = {id(n): f"{n.nodeid} ({n.browsename})" for n in kept}
            return super().make_objects(kept)

        async def _add_node_data(self, nodedata: Any, no_namespace_migration: bool = False) -> Any:
            try:
                return await super()._add_node_data(nodedata, no_namespace_migration)
            except Exception as exc:  # noqa: BLE001 - any failure of one node: name it
                node = self.written.get(id(nodedata), f"{nodedata.nodeid} ({nodedata.browsename})")
                raise NodesetError(f"{self.nodeset.path}: node {node}: {_reason(exc)}") from None

    return Importer


def _reason(exc: BaseException) -> str:
    # asyncua's status errors say their code's name in their text: "... (BadParentNodeIdInvalid)"
    return f"{type(exc).__name__}: {exc}"


async def import_nodesets(server: Any, folder: Path) -> list[Nodeset]:
    """Import the six models from `folder` into `server` (initialised, not started). Raises NodesetError."""
    nodesets = find_nodesets(folder)
    importer = _importer_class()
    started = time.monotonic()
    for nodeset in nodesets:
        try:
            await importer(server, nodeset).import_xml(str(nodeset.path))
        except NodesetError:
            raise
        except Exception as exc:  # noqa: BLE001 - a file-level failure (its required models, its references)
            raise NodesetError(f"{nodeset.path}: {_reason(exc)}") from None
    try:
        await server.load_data_type_definitions()
    except Exception as exc:  # noqa: BLE001
        raise NodesetError(f"{folder}: the data types of the imported nodesets cannot be loaded: {_reason(exc)}") from None
    log.info("opcua.nodesets_loaded", folder=str(folder), seconds=round(time.monotonic() - started, 2),
             models=[f"{n.name} {n.version} ({n.path.name})" for n in nodesets])
    return nodesets
