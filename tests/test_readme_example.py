"""The README's Python example, run as written against the compose deployment.

The services of docker-compose.yml run as local processes (`tests.test_compose`), with the
accounts and keys deploy/security/compose-accounts.sh makes. A participant account is
added as the README says (deploy/security/make-passwd.sh, then the user-cluster broker
restarted), and the README's Python code block runs in a fresh interpreter with the
environment the README tells the reader to set.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_compose import ACCOUNTS, LocalCompose, start_order
from tests.test_compose import local_compose as local_compose

README = Path(__file__).resolve().parents[1] / "README.md"
HEADING = "## Use it from Python"


def readme_example() -> str:
    """The first Python code block under the README's Python heading."""
    text = README.read_text()
    assert HEADING in text, f"README.md has no {HEADING!r} section"
    found = re.search(r"```python\n(.*?)```", text.split(HEADING, 1)[1], re.DOTALL)
    assert found, f"no python block under {HEADING!r}"
    return found[1]


def test_the_readme_names_the_variables_its_example_reads() -> None:
    section = README.read_text().split(HEADING, 1)[1].split("\n## ", 1)[0]
    for name in ("LAAS_CLUSTER", "LAAS_USERNAME", "LAAS_PASSWORD"):
        assert name in section, name
    assert "laas.Client" in readme_example()


def test_the_readmes_files_links_profiles_and_services_exist() -> None:
    """Every file the README and the project files link or run exists, and every compose
    profile and service the README names is in docker-compose.yml."""
    import yaml  # type: ignore[import-untyped]

    root = README.parent
    pages = [README, root / "SECURITY.md", root / "CHANGELOG.md"]
    pages += [root / "docs" / f"{name}.md" for name in ("design", "performance", "scaling")]
    for page in pages:
        for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", page.read_text()):
            assert (page.parent / target).exists(), f"{page.name}: {target}"
    text = README.read_text()
    for script in re.findall(r"((?:deploy|scripts)/[\w./-]+\.(?:sh|py))", text):
        assert (root / script).is_file(), script
    services = yaml.safe_load((root / "docker-compose.yml").read_text())["services"]
    profiles = {p for s in services.values() for p in s.get("profiles", [])}
    named = set(re.findall(r"--profile (\w+)", text))
    assert named and named <= profiles, (named, profiles)
    for service in re.findall(r"docker compose (?:restart|--profile \w+ up) (\w[\w-]*)", text):
        assert service in services, service


@pytest.mark.mosquitto
@pytest.mark.timeout(120)
def test_the_readme_python_example_runs_against_the_compose_deployment(
    local_compose: LocalCompose,
) -> None:
    services = local_compose.services
    for name in [n for n in start_order(services) if not services[n].get("profiles")]:
        local_compose.start(name)
        local_compose.wait_healthy(name)
    # README, "Add participants": an account for the program, then the broker restarted
    added = subprocess.run(
        ["bash", str(ACCOUNTS.parent / "make-passwd.sh"), str(local_compose.passwd), "bike-42"],
        capture_output=True,
        text=True,
        check=True,
        env={"PATH": "/usr/bin:/bin", "MODE": "0644"},
    )
    user, _, password = added.stdout.strip().partition("=")
    assert user == "bike-42" and len(password) >= 16, added.stdout
    local_compose.stop("broker-user")
    local_compose.start("broker-user")
    local_compose.wait_healthy("broker-user")
    local_compose.wait_healthy("core-user")

    env = {
        "PATH": "/usr/bin:/bin",
        "LAAS_CLUSTER": f"mqtt://127.0.0.1:{local_compose.ports['broker-user']}",
        "LAAS_USERNAME": user,
        "LAAS_PASSWORD": password,
        "LAAS_SERVICE_KEY": local_compose.secrets["LAAS_SERVICE_KEY"],
        "LAAS_CORE_KEY": local_compose.secrets["LAAS_CORE_KEY"],
    }
    result = subprocess.run(
        [sys.executable, "-c", readme_example()],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=local_compose.workdir,
    )
    assert result.returncode == 0, result.stderr + local_compose.log("worker")
    assert re.fullmatch(r"messe-\d+ \d+ driving \d+\.\d\d m\n", result.stdout), result.stdout
    assert password not in result.stdout + result.stderr
    assert local_compose.stop("worker") == 0
    assert re.search(r"stopped; 1 answered", local_compose.log("worker")), local_compose.log(
        "worker"
    )
