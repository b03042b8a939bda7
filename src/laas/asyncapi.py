"""Moved to `laas.worker.asyncapi` (the worker's package); `laas.asyncapi` names the same
objects for the code that imports them from here."""

from laas.worker.asyncapi import (
    DOCUMENT,
    laas_document,
    laas_document_text,
    write_document,
)

__all__ = [
    "DOCUMENT",
    "laas_document",
    "laas_document_text",
    "write_document",
]
