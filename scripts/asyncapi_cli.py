"""Validate docs/asyncapi.json with the AsyncAPI CLI (a command, not a test).

The test command checks the document in process: it is what `laas asyncapi` writes, it
is valid by the AsyncAPI 3.0 JSON schema (tests/data/asyncapi), and it follows the
topics and models (tests/test_asyncapi.py). The CLI's own validation adds the AsyncAPI
parser's rules; it takes about a minute (node, and npx fetching the CLI), and checks a
document rather than the software's behaviour, so it is this command, which CI runs
after the test command (.ci/run):

    .venv/bin/python scripts/asyncapi_cli.py     # exit 0: "is valid"

It uses `asyncapi` from PATH, else `npx -y @asyncapi/cli@6.2.0`; with neither it fails
(exit 2) saying what to install.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCUMENT = ROOT / "docs" / "asyncapi.json"
CLI_PACKAGE = "@asyncapi/cli@6.2.0"


def cli() -> list[str] | None:
    if shutil.which("asyncapi"):
        return ["asyncapi"]
    npx = shutil.which("npx")
    return [npx, "-y", CLI_PACKAGE] if npx else None


def main() -> int:
    command = cli()
    if command is None:
        print(
            f"neither asyncapi nor npx is on PATH: `npm install --global {CLI_PACKAGE}`",
            file=sys.stderr,
        )
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        analytics = Path(tmp) / "asyncapi-analytics.json"  # the CLI sends no usage data
        analytics.write_text('{"analyticsEnabled": "false", "infoMessageShown": "true"}')
        result = subprocess.run(
            [*command, "validate", str(DOCUMENT), "--fail-severity", "warn"],
            capture_output=True,
            text=True,
            timeout=580,
            cwd=tmp,
            env={
                **os.environ,
                "ASYNCAPI_METRICS_CONFIG_PATH": str(analytics),
                "SUPPRESS_NO_CONFIG_WARNING": "1",
            },
        )
    output = result.stdout + result.stderr
    print(output.strip())
    if result.returncode != 0 or "is valid" not in output:
        print("docs/asyncapi.json: the AsyncAPI CLI did not find it valid", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
