"""docs/asyncapi.json: what `laas asyncapi` writes, valid AsyncAPI 3.0 (by the JSON schema
kept in tests/data/asyncapi), and true to the topics and models it describes. The
AsyncAPI CLI's validation (about a minute, a check of the document, not of behaviour)
is a command that CI runs after the tests: `python scripts/asyncapi_cli.py`."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from jsonschema import Draft7Validator  # type: ignore[import-untyped]

from laas.cli import main
from laas.models import CorrectedPosition, ErrorReply, GpsMeasurement
from ldm.wire import topics

ROOT = Path(__file__).resolve().parents[1]
DOCUMENT = ROOT / "docs" / "asyncapi.json"
SCHEMA = ROOT / "tests" / "data" / "asyncapi" / "asyncapi-3.0.0.schema.json"
CLI_PACKAGE = "@asyncapi/cli@6.2.0"
_NETWORK = re.compile(r"ENOTFOUND|EAI_AGAIN|ECONNREFUSED|ETIMEDOUT|ENETUNREACH")


def load() -> dict[str, Any]:
    doc: dict[str, Any] = json.loads(DOCUMENT.read_text(encoding="utf-8"))
    return doc


def test_the_committed_document_is_what_laas_asyncapi_writes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "asyncapi.json"
    assert main(["asyncapi", "--out", str(out)]) == 0
    assert out.read_text(encoding="utf-8") == DOCUMENT.read_text(encoding="utf-8"), (
        "docs/asyncapi.json is out of date: run `laas asyncapi --out docs/asyncapi.json`"
    )
    capsys.readouterr()
    assert main(["asyncapi"]) == 0
    assert capsys.readouterr().out == out.read_text(encoding="utf-8")


def test_the_document_is_valid_by_the_asyncapi_3_json_schema() -> None:
    validator = Draft7Validator(json.loads(SCHEMA.read_text(encoding="utf-8")))
    doc = load()
    errors = [f"{list(e.absolute_path)}: {e.message}" for e in validator.iter_errors(doc)]
    assert errors == []
    doc["operations"]["providerReplies"]["action"] = "publish"  # AsyncAPI 2's word
    assert list(validator.iter_errors(doc)), "the schema must catch a wrong document"


def test_the_document_follows_the_topics_and_the_models() -> None:
    doc = load()
    addresses = {c["address"] for c in doc["channels"].values()}
    c, s, p = "{client}", "{service}", "{pseudonym}"
    assert {
        topics.SERVICES,
        topics.services_request(c),
        topics.services_reply(c),
        topics.session_request(c),
        topics.session_notice(c),
        topics.participant_input(c, s),
        topics.participant_reply(c, s),
        topics.announce(s),
        topics.provider_input(s, p),
        topics.provider_reply(s, p),
        topics.bb_announce(s),
        topics.bb_core("{core}"),
        topics.bb_input("{svc_core}", s, "{user_core}", p),
        topics.bb_reply("{user_core}", s, p),
        "ldm/p/{client}/up/data/laas",
        "ldm/svc/laas/out/{pseudonym}",
    } <= addresses
    for channel in doc["channels"].values():  # every {parameter} is described
        assert set(re.findall(r"{(\w+)}", channel["address"])) == set(channel.get("parameters", {}))
    schemas = doc["components"]["schemas"]
    for model in (GpsMeasurement, CorrectedPosition, ErrorReply):
        own = model.model_json_schema(ref_template="#/components/schemas/{model}")
        own.pop("$defs", None)
        assert schemas[model.__name__] == own
    fix = doc["components"]["messages"]["LaasInput"]
    assert fix["x-ldm-plaintext"] == {"$ref": "#/components/schemas/GpsMeasurement"}
    assert fix["payload"] == {"$ref": "#/components/schemas/Envelope"}
