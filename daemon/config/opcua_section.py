"""`[opcua]` (issue 42, additive): the OPC UA server's settings, read by `millsense opcua --config FILE`.

The daemon ignores the section (it never imports asyncua); `check-config` checks it like any other. The
command line's options override it key by key. Paths are taken from the config file's folder when relative.

Identification: OPC 40001-1 makes a MachineToolType's Manufacturer, SerialNumber and ProductInstanceUri
mandatory, and millsense cannot know them: with `nodesets_dir` set the three are required here, for this
file's `machine` (docs/opcua.md: use the CNC's own ProductInstanceUri so aggregators merge the two models).
"""

from __future__ import annotations

from urllib.parse import urlparse

from pydantic import Field, field_validator, model_validator

from millsense.daemon.config.models import _Section, problems_error

DEFAULT_ENDPOINT = "opc.tcp://127.0.0.1:4840"
IDENTIFICATION_KEYS = ("manufacturer", "serial_number", "product_instance_uri")


def opcua_endpoint_problem(text: str) -> str | None:
    """Why `text` is not `opc.tcp://HOST:PORT`, or None."""
    url = urlparse(text)
    if url.scheme != "opc.tcp":
        return f"{text!r} is not opc.tcp://HOST:PORT"
    try:
        url.port  # noqa: B018 - raises for a port that is not a number 1-65535
    except ValueError:
        return f"{text!r}: the port is not a number 1-65535"
    if not url.hostname:
        return f"{text!r} names no host ({DEFAULT_ENDPOINT})"
    if url.path not in ("", "/") or url.query:
        return f"{text!r}: give only opc.tcp://HOST:PORT"
    return None


class OpcuaSettings(_Section):
    """`[opcua]`: where `millsense opcua` listens, its certificates, the nodesets, this machine's identity."""

    endpoint: str = DEFAULT_ENDPOINT
    cert: str = ""
    key: str = ""
    trust_dir: str = ""
    operators_dir: str = ""   # the certificates (each also in trust_dir) that may acknowledge and confirm alarms
    nodesets_dir: str = ""
    allow_anonymous: bool = False
    manufacturer: str = Field("", max_length=256)
    serial_number: str = Field("", max_length=256)
    product_instance_uri: str = Field("", max_length=1024)

    @field_validator("endpoint")
    @classmethod
    def _endpoint(cls, value: str) -> str:
        problem = opcua_endpoint_problem(value)
        if problem:
            raise ValueError(problem)
        return value

    @model_validator(mode="after")
    def _identified(self) -> OpcuaSettings:
        problems = []
        if self.nodesets_dir:
            for key in IDENTIFICATION_KEYS:
                if not getattr(self, key).strip():
                    problems.append((key, "missing: nodesets_dir makes each machine an OPC 40501 MachineToolType, whose "
                                          "Identification needs manufacturer, serial_number and product_instance_uri"))
        uri = self.product_instance_uri
        if uri and (not urlparse(uri).scheme or any(c.isspace() for c in uri)):
            problems.append(("product_instance_uri", f"{uri!r} is not a URI (the CNC's own ProductInstanceUri, or e.g. "
                                                     "urn:<manufacturer>:<serial number>; OPC 40001-1)"))
        if problems:
            raise problems_error(problems)
        return self
