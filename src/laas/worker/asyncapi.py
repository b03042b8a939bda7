"""`laas asyncapi`: the AsyncAPI 3.0 document of the LDM and of the `laas` service.

Built by `ldm.wire.asyncapi` from the LDM's topics and messages and from `laas.models`, so
it cannot drift from the code; docs/asyncapi.json is this document, committed (a test
checks it is current and valid).
"""

from __future__ import annotations

from importlib.metadata import version
from pathlib import Path
from typing import Any

from laas.models import CorrectedPosition, ErrorReply, GpsMeasurement
from laas.worker.service import SERVICE_NAME
from ldm.wire.asyncapi import ServiceApi, document, render

__all__ = ["DOCUMENT", "laas_document", "laas_document_text", "write_document"]

DOCUMENT = Path("docs") / "asyncapi.json"
"""Where the repository keeps the document, relative to its root."""

_DESCRIPTION = (
    "LaaS (Location as a Service) over the LDM, a service architecture on MQTT. Road "
    "users are LDM participants: they find the `laas` service in the retained service "
    "list, open a session with their user-cluster core and send GNSS fixes "
    "(GpsMeasurement), encrypted end to end in an Envelope (X25519, HKDF-SHA256, "
    "ChaCha20-Poly1305; see docs/ldm.md), and get back a lane-precise CorrectedPosition "
    "or an ErrorReply. Cores route the ciphertext by pseudonym and never read it; the "
    "service never learns the participant's client id. The `x-ldm-plaintext` of a "
    "message is the schema of what its `d` decrypts to."
)


def laas_document() -> dict[str, Any]:
    """The document, as a dict."""
    api = ServiceApi(
        name=SERVICE_NAME,
        description="A road user's GNSS fix.",
        input=GpsMeasurement,
        outputs=(CorrectedPosition, ErrorReply),
    )
    return document(
        title="LaaS over the LDM",
        version=version("laas"),
        description=_DESCRIPTION,
        services=[api],
    )


def laas_document_text() -> str:
    """The document as `laas asyncapi` writes it (JSON)."""
    return render(laas_document())


def write_document(path: Path) -> Path:
    """Write the document to `path` (folders made as needed); returns the path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(laas_document_text(), encoding="utf-8")
    return path
