"""The OPC UA tests need the `opcua` extra (asyncua). Without it they skip on a developer's box; under
CI=true they fail instead, so that a CI image that lost the extra cannot pass by skipping them."""

from __future__ import annotations

import importlib.util
import os

if importlib.util.find_spec("asyncua") is None and os.environ.get("CI") == "true":
    raise RuntimeError("CI=true: the OPC UA tests need asyncua: pip install -e '.[opcua]'")
