"""docker-compose.yml, run without Docker: every service as a local process.

There is no container engine on the test machines, so this test reads the compose file
and starts each service with the same command, arguments and environment as compose
would: the brokers as Mosquitto processes with the mounted config, ACL and password file
(only the listener port changes, a free port per broker, and the mounted paths become
the host files), the Python services through the same console scripts. The accounts and
keys are made as the deployment makes them: deploy/security/compose-accounts.sh writes
an env file with random passwords and the public identity keys, the password file and
the private keys, and the env file's values are what compose would substitute. Service
host names (`broker-user`, ...) become 127.0.0.1:<that broker's port>, paths a Python
service mounts (its identity key) become the host files, and image paths under /app/
become the repository's.
Dependencies start in compose's order and wait for the compose health checks, which run
here too. Then the simulator (profile `sim`) drives the Hamburg road users through the
deployment.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest
import yaml  # type: ignore[import-untyped]

from ldm.config import CoreConfig
from ldm.local.brokers import find_mosquitto, free_port
from ldm.local.pytest_plugin import need_mosquitto, need_nats

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
CLUSTER = ROOT / "docker-compose.cluster.yml"  # the service cluster on NATS, an override
TLS = ROOT / "docker-compose.tls.yml"  # the user-cluster broker's TLS listener, an override
LISTENERS = ROOT / "deploy" / "mosquitto" / "listeners.d"  # included by mosquitto.conf
ACCOUNTS = ROOT / "deploy" / "security" / "compose-accounts.sh"
PASSWD = ROOT / "deploy" / "security" / "passwd"
KEYS = ROOT / "deploy" / "security" / "keys"
HEALTH = ROOT / "deploy" / "security" / "health"  # the brokers' health check options
# identity key file -> the env variable with its public key (None: no one pins it)
KEY_FILES = {"laas-worker": "LAAS_SERVICE_KEY", "core-user": "LAAS_CORE_KEY", "core-service": None}
MOSQUITTO_IMAGE = "eclipse-mosquitto:2.0.18"
CONFIG_IN_IMAGE = "/mosquitto/config/mosquitto.conf"
_VARIABLE = re.compile(r"\$\$|\$\{(\w+)(?:(:?[-?])([^}]*))?\}|\$(\w+)")

Service = dict[str, Any]


class Unset(Exception):
    """A required variable (${X:?message}, ${X?message}) is unset: compose refuses."""


def interpolate(value: Any, env: Mapping[str, str]) -> Any:
    """Compose's substitution: ${X}, ${X:-default}, ${X-default}, ${X:?err}, ${X?err}, $X, $$."""
    if isinstance(value, str):

        def sub(m: re.Match[str]) -> str:
            if m.group(0) == "$$":
                return "$"
            name = m.group(1) or m.group(4)
            if m.group(2) == ":-":
                return env.get(name) or m.group(3)
            if m.group(2) == "-":
                return env.get(name, m.group(3))
            if m.group(2) in (":?", "?"):
                found = env.get(name)
                if found is None or (m.group(2) == ":?" and not found):
                    raise Unset(f"{name}: {m.group(3)}")
                return found
            return env.get(name, "")

        return _VARIABLE.sub(sub, value)
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    return value


def merge(base: Any, override: Any) -> Any:
    """Compose's merge of a later file over an earlier one: mappings merged key by key,
    `volumes` by their target (a later mount replaces one at the same path), `profiles`
    and `ports` (and other sequences) appended, other values replaced; a service's
    `command` and health check `test` are replaced whole."""
    if isinstance(base, dict) and isinstance(override, dict):
        merged = dict(base)
        for key, value in override.items():
            if key in ("command", "test") or key not in merged:
                merged[key] = value
            elif key == "volumes" and isinstance(value, list):
                by_target = {_target(v): v for v in merged[key]}
                by_target.update({_target(v): v for v in value})
                merged[key] = list(by_target.values())
            else:
                merged[key] = merge(merged[key], value)
        return merged
    if isinstance(base, list) and isinstance(override, list):
        return base + [v for v in override if v not in base]
    return override


def _target(volume: str | dict[str, Any]) -> str:
    return str(volume["target"]) if isinstance(volume, dict) else str(volume).split(":")[1]


def load_compose(env: Mapping[str, str] | None = None, *overrides: Path) -> dict[str, Service]:
    """The services of docker-compose.yml (merged with `overrides`, as `docker compose
    -f docker-compose.yml -f OVERRIDE` merges them), variables substituted from `env`."""
    data = yaml.safe_load(COMPOSE.read_text())
    for path in overrides:
        data = merge(data, yaml.safe_load(path.read_text()))
    services: dict[str, Service] = interpolate(data["services"], env or {})
    return services


def enabled(services: Mapping[str, Service], *profiles: str) -> set[str]:
    """The services compose starts with `profiles` active."""
    return {
        n
        for n, s in services.items()
        if not s.get("profiles") or set(s["profiles"]) & set(profiles)
    }


def is_broker(service: Service) -> bool:
    return bool(service.get("image") == MOSQUITTO_IMAGE)


def is_nats(service: Service) -> bool:
    """A node of the service cluster on NATS (docker-compose.cluster.yml)."""
    return str(service.get("image", "")).startswith("nats:")


def mounts(service: Service) -> dict[str, Path]:
    """Path in the container -> the host file mounted there (short or long syntax)."""
    found = {}
    for volume in service.get("volumes", []):
        if isinstance(volume, dict):
            assert volume["type"] == "bind", volume
            source, target = volume["source"], volume["target"]
        else:
            source, target, *_ = str(volume).split(":")
        found[target] = (ROOT / source).resolve()
    return found


def read_only(volume: str | dict[str, Any]) -> bool:
    if isinstance(volume, dict):
        return volume.get("read_only") is True
    return volume.endswith(":ro")


def mounted_config(service: Service) -> Path:
    """The host file a broker service mounts as its mosquitto.conf."""
    config = mounts(service).get(CONFIG_IN_IMAGE)
    assert config, f"broker mounts no {CONFIG_IN_IMAGE}: {service.get('volumes')}"
    return config


def settings(config: Path) -> list[tuple[str, str]]:
    """The (option, value) lines of a mosquitto.conf, in order, comments dropped."""
    lines = [line.split("#")[0].strip() for line in config.read_text().splitlines()]
    return [(k, v.strip()) for k, _, v in (line.partition(" ") for line in lines if line)]


def make_accounts(directory: Path) -> dict[str, str]:
    """Run compose-accounts.sh as documented, into `directory`; the env file's values.

    The password file is `directory`/passwd, the identity keys are in `directory`/keys.
    """
    env_file, passwd = directory / ".env", directory / "passwd"
    subprocess.run(
        ["bash", str(ACCOUNTS), str(env_file)],
        check=True,
        capture_output=True,
        env={
            "PATH": "/usr/bin:/bin:/usr/sbin",
            "PASSWD_FILE": str(passwd),
            "MODE": "0644",
            "KEYS_DIR": str(directory / "keys"),
            "HEALTH_DIR": str(directory / "health"),
        },
    )
    values = {}
    for line in env_file.read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, value = line.partition("=")
            values[name] = value
    return values


def environment(service: Service) -> dict[str, str]:
    env = service.get("environment", {})
    if isinstance(env, list):
        env = dict(item.split("=", 1) for item in env)
    return {k: "" if v is None else str(v) for k, v in env.items()}


def start_order(services: Mapping[str, Service]) -> list[str]:
    """Services in an order where each comes after everything it depends on."""
    order: list[str] = []

    def visit(name: str, seen: tuple[str, ...]) -> None:
        assert name not in seen, f"dependency cycle: {' -> '.join((*seen, name))}"
        if name in order:
            return
        for dep in services[name].get("depends_on", {}):
            visit(dep, (*seen, name))
        order.append(name)

    for name in services:
        visit(name, ())
    return order


# --- the file's promises -------------------------------------------------------------


def test_every_service_restarts_and_brokers_are_checked() -> None:
    services = load_compose(SETTINGS)
    brokers = [n for n, s in services.items() if is_broker(s)]
    assert sorted(brokers) == ["broker-backbone", "broker-service", "broker-user"]
    for name, service in services.items():
        assert service.get("restart") in ("unless-stopped", "always", "on-failure"), name
        for dep, how in service.get("depends_on", {}).items():
            assert dep in services, f"{name} depends on unknown {dep}"
            assert how == {"condition": "service_healthy"}, (name, dep)
            assert "healthcheck" in services[dep], f"{name} waits on {dep}, which has no check"
    for name in brokers:
        assert services[name]["healthcheck"]["test"][0] == "CMD", name
    for name, service in services.items():
        if not is_broker(service) and "sim" not in service.get("profiles", []):
            assert service["restart"] == "unless-stopped", name
            assert "healthcheck" in service, name
            assert isinstance(service["command"], list), f"{name}: use the exec form"
    assert services["simulator"]["profiles"] == ["sim"]
    # only the user-cluster broker faces the participants
    assert [n for n, s in services.items() if s.get("ports")] == ["broker-user"]


SECRETS = {
    "LDM_CORE_USER_PASSWORD": "u",
    "LDM_CORE_SERVICE_PASSWORD": "s",
    "LAAS_WORKER_PASSWORD": "w",
    "LAAS_HEALTH_PASSWORD": "h",
    "LAAS_SIM_PASSWORD": "p",
    "LAAS_OWNTRACKS_PASSWORD": "o",
    "LAAS_CAM_PASSWORD": "c",
    "LAAS_DEVICE_PASSWORD": "d",
}
PUBLIC_KEYS = {"LAAS_SERVICE_KEY": "service-key=", "LAAS_CORE_KEY": "core-key="}
SETTINGS = {**SECRETS, **PUBLIC_KEYS}  # what compose-accounts.sh puts in .env


def test_every_mosquitto_config_in_use_is_tuned_and_locked() -> None:
    services = load_compose(SETTINGS)
    brokers = {n: s for n, s in services.items() if is_broker(s)}
    acls = {
        "broker-user": "deploy/security/acl-user-cluster",
        "broker-backbone": "deploy/security/acl-backbone",
        "broker-service": "deploy/security/acl-service-cluster",
    }
    assert sorted(brokers) == sorted(acls)
    for name, service in brokers.items():
        config = mounted_config(service)
        options = settings(config)
        found = dict(options)
        assert found.get("set_tcp_nodelay") == "true", config
        assert ("listener", "1883") in options, config
        assert found.get("persistence") in ("false", "true"), config
        assert found.get("max_packet_size") == "66560", config  # 64 KiB payload + 1 KiB
        assert "message_size_limit" not in found, config  # deprecated: Mosquitto warns
        # anonymous access is off; every broker has its accounts and ACL, mounted
        assert [v for k, v in options if k == "allow_anonymous"] == ["false"], config
        files = mounts(service)
        for option, in_image, host in (
            ("password_file", "/mosquitto/config/passwd", "deploy/security/passwd"),
            ("acl_file", "/mosquitto/config/acl", acls[name]),
        ):
            assert found.get(option) == in_image, (config, option)
            assert files.get(in_image) == ROOT / host, (name, in_image)
            assert all(read_only(v) for v in service["volumes"]), name
    assert mounted_config(brokers["broker-user"]) == ROOT / "mosquitto.conf"
    assert len({mounted_config(s) for s in brokers.values()}) == 3, "one config per broker"


def listener_blocks(lines: list[tuple[str, str]]) -> list[list[tuple[str, str]]]:
    """The options of each listener block (from a `listener` line to the next)."""
    blocks: list[list[tuple[str, str]]] = []
    for option in lines:
        if option[0] == "listener":
            blocks.append([])
        elif blocks:
            blocks[-1].append(option)
    return blocks


def test_every_user_cluster_listener_uses_the_user_name_as_client_id() -> None:
    config = mounted_config(load_compose(SETTINGS)["broker-user"])
    blocks = listener_blocks(settings(config))
    assert blocks, "no listener"
    for block in blocks:
        assert ("use_username_as_clientid", "true") in block, config
    # ... and so do the listeners it includes: none by default, the TLS overlay's
    included = dict(settings(config))["include_dir"]
    assert mounts(load_compose(SETTINGS)["broker-user"])[included] == LISTENERS
    assert list(LISTENERS.glob("*.conf")) == []
    tls = load_compose(SETTINGS, TLS)["broker-user"]
    tls_blocks = listener_blocks(settings(mounts(tls)[included] / "tls.conf"))
    assert [b for b in tls_blocks if ("certfile", "/mosquitto/certs/server.crt") in b]
    for block in tls_blocks:
        assert ("use_username_as_clientid", "true") in block, block


def acl_rules(path: Path) -> list[tuple[str | None, str]]:
    """(user the rule belongs to, None for every client's patterns/anonymous; the rule)."""
    user: str | None = None
    rules = []
    for line in path.read_text().splitlines():
        line = "" if line.lstrip().startswith("#") else line.strip()  # topics hold "#"
        if line.startswith("user "):
            user = line.split(None, 1)[1]
        elif line:
            rules.append((user, line))
    return rules


def test_the_acls_give_every_compose_account_what_it_needs() -> None:
    security = ROOT / "deploy" / "security"
    for acl in security.glob("acl-*"):
        rules = acl_rules(acl)
        # before the first `user` line, a `topic` rule binds only anonymous clients
        assert not [r for u, r in rules if u is None and r.startswith("topic")], acl
        assert ("laas-health", "topic read $SYS/broker/version") in rules, acl
    user = acl_rules(security / "acl-user-cluster")
    # no pattern without %u: Mosquitto warns at every start (the list comes per client)
    assert [r for u, r in user if u is None and r.startswith("pattern") and "%u" not in r] == []
    assert (None, "pattern write ldm/p/%u/up/#") in user
    assert not (ROOT / "deploy" / "mosquitto" / "acl.example").exists()
    # the accounts the compose services log in with exist in their brokers' ACLs
    services = load_compose(SETTINGS)
    for name in ("user", "service"):
        command = services[f"core-{name}"]["command"]
        account = f"ldm-core-{name}"
        assert command[command.index("--username") + 1] == account
        assert command[command.index("--backbone-username") + 1] == account
        assert account in {u for u, _ in acl_rules(security / f"acl-{name}-cluster")}
        assert account in {u for u, _ in acl_rules(security / "acl-backbone")}
        env = environment(services[f"core-{name}"])
        assert (
            env["LDM_PASSWORD"]
            == env["LDM_BACKBONE_PASSWORD"]
            == SECRETS[f"LDM_CORE_{name.upper()}_PASSWORD"]
        )
        assert command[command.index("--rate") + 1] == _default("rate")
        assert command[command.index("--burst") + 1] == _default("burst")
    assert environment(services["worker"])["LAAS_USERNAME"] == "laas-worker"
    assert environment(services["simulator"])["LAAS_DEVICE_PASSWORD"] == "p"
    # no password on a command line, not even the broker health check's (laas-health)
    for name, service in services.items():
        words = (
            [*service.get("command", []), *service["healthcheck"]["test"]]
            if ("healthcheck" in service)
            else list(service.get("command", []))
        )
        leaked = {w for w in words if w in SECRETS.values()}
        assert leaked == set(), name
    # the health check's password reaches mosquitto_sub in a mounted option file
    for name, service in services.items():
        if is_broker(service):
            options = mounts(service)["/mosquitto/health/mosquitto_sub"]
            assert options == HEALTH / "mosquitto_sub", name
            assert environment(service)["XDG_CONFIG_HOME"] == "/mosquitto/health", name


def test_compose_refuses_to_start_without_passwords_or_keys() -> None:
    with pytest.raises(Unset, match=re.escape("compose-accounts.sh")):
        load_compose({})
    for name in SETTINGS:
        if name == "LAAS_HEALTH_PASSWORD":  # in the health check's option file instead
            continue
        for missing in ({k: v for k, v in SETTINGS.items() if k != name}, {**SETTINGS, name: ""}):
            with pytest.raises(Unset, match=re.escape(f"{name}: unset; run deploy/security/")):
                load_compose(missing)


def image_uid() -> int:
    """The uid the Python image runs as (the Dockerfile's `useradd --uid`)."""
    found = re.search(r"useradd [^\n]*--uid (\d+)", (ROOT / "Dockerfile").read_text())
    assert found, "Dockerfile: no useradd --uid"
    return int(found[1])


PARTICIPANTS = ("simulator", "owntracks", "cam")  # services that are participants


def test_every_python_service_has_its_own_key_and_pins_the_worker() -> None:
    services = load_compose(SETTINGS, CLUSTER)
    keys = {}
    for name, service in services.items():
        if is_broker(service) or is_nats(service):
            continue
        # the key, mounted read-only where the program is told to find it; the host file
        # must exist (long syntax, create_host_path false: no empty directory instead)
        files = {t: h for t, h in mounts(service).items() if h.parent == KEYS}
        assert all(read_only(v) for v in service.get("volumes", [])), name
        for volume in service.get("volumes", []):
            assert isinstance(volume, dict) and volume["bind"]["create_host_path"] is False
        command, env = service["command"], environment(service)
        if name in PARTICIPANTS:
            assert not files, f"{name} is a participant: public keys only"
            assert env["LAAS_SERVICE_KEY"] == PUBLIC_KEYS["LAAS_SERVICE_KEY"]
            assert env["LAAS_CORE_KEY"] == PUBLIC_KEYS["LAAS_CORE_KEY"]
            continue
        assert len(files) == 1, (name, files)
        [(target, host)] = files.items()
        assert command[command.index("--identity") + 1] == target, name
        keys[name] = host.name
        if command[:2] == ["ldm", "core"]:
            pins = [command[i + 1] for i, w in enumerate(command) if w == "--trust-service"]
            assert pins == [f"laas={PUBLIC_KEYS['LAAS_SERVICE_KEY']}"], name
    # The cluster override: the service core on NATS stands in for core-service, and the
    # regional workers and their standbys are the one laas service (pinned once), so
    # they mount the same keys.
    regional = ("worker-1of2", "worker-2of2", "worker-1of2-standby", "worker-2of2-standby")
    assert keys == {
        "core-user": "core-user.key",
        "core-service": "core-service.key",
        "worker": "laas-worker.key",
        "core-service-cluster": "core-service.key",
        **{name: "laas-worker.key" for name in regional},
    }
    assert sorted(set(keys.values())) == sorted(f"{k}.key" for k in KEY_FILES)
    # the private keys are never committed
    assert "/deploy/security/keys/" in (ROOT / ".gitignore").read_text().split()


def _default(field: str) -> str:
    """A CoreConfig default as the compose file spells it (a whole number)."""
    return f"{CoreConfig.model_fields[field].default:g}"


def test_cores_and_worker_match_the_topology() -> None:
    services = load_compose(SETTINGS)
    for name in ("user", "service"):
        command = services[f"core-{name}"]["command"]
        assert command[:4] == ["ldm", "core", "--name", name]
        assert command[command.index("--cluster") + 1] == f"mqtt://broker-{name}:1883"
        assert command[command.index("--backbone") + 1] == "mqtt://broker-backbone:1883"
        assert command[command.index("--rotation-period") + 1] == "120"
    user_core = services["core-user"]["command"]  # the core that grants sessions
    assert user_core[user_core.index("--rotation") + 1] == "epoch"
    flag = {f: user_core[user_core.index(f) + 1] for f in ("--silence", "--silence-max")}
    assert flag == {"--silence": "30", "--silence-max": "90"}
    # the core takes that policy: its longest silence under half the period and idle_timeout
    CoreConfig(
        name="user",
        cluster="mqtt://broker-user:1883",
        rotation_period=float(user_core[user_core.index("--rotation-period") + 1]),
        idle_timeout=float(user_core[user_core.index("--idle-timeout") + 1]),
        rotation={"strategy": "epoch", "silence": 30.0, "silence_max": 90.0},
    )
    worker = services["worker"]
    assert worker["command"][:2] == ["laas", "worker"]
    assert environment(worker)["LAAS_CLUSTER"] == "mqtt://broker-service:1883"
    sim = services["simulator"]["command"]
    assert sim[:2] == ["laas", "simulate"]
    assert "--device-accounts" in sim and sim[sim.index("--prefix") + 1] == "sim-"
    assert sim[sim.index("--cluster") + 1] == "mqtt://broker-user:1883"
    # configuration by environment
    changed = load_compose({**SETTINGS, "LDM_ROTATION_PERIOD": "30", "LAAS_LOG_LEVEL": "debug"})
    command = changed["core-user"]["command"]
    assert command[command.index("--rotation-period") + 1] == "30"
    assert environment(changed["worker"])["LAAS_LOG_LEVEL"] == "debug"


def test_dockerfile_builds_a_non_root_image_without_entrypoint() -> None:
    lines = [
        line.strip()
        for line in (ROOT / "Dockerfile").read_text().splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
    assert lines[0] == "FROM python:3.11-slim"
    assert any(re.match(r"RUN pip install \.(\s|$)", line) for line in lines)
    assert not any(line.startswith("ENTRYPOINT") for line in lines)
    users = [line.split()[1] for line in lines if line.startswith("USER")]
    assert users and users[-1] not in ("root", "0")
    # what the compose file runs from the image is copied into it
    copied = " ".join(line for line in lines if line.startswith("COPY"))
    for path in ("pyproject.toml", "src", "maps", "deploy/healthcheck.py"):
        assert path in copied, path
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert ".venv" in ignored and ".git" in ignored
    assert ".env" in ignored and "deploy/security/passwd" in ignored


def test_interpolation_follows_compose() -> None:
    env = {"A": "1", "E": ""}
    assert interpolate("${A:-x} ${B:-x} ${E:-x} ${E-x} ${B-y} $A $$SYS", env) == "1 x x  y 1 $SYS"
    assert interpolate("${A:?no} ${E?no}", env) == "1 "
    for unset in ("${E:?no}", "${B?no}"):
        with pytest.raises(Unset):
            interpolate(unset, env)


def settings_lines(text: str) -> list[str]:
    """Each line of an env file, values dropped: its comments and variables, in order."""
    return [line.split("=")[0] for line in text.splitlines()]


def show_key(path: Path) -> str:
    """`ldm keys show`: the public key of a private key file."""
    return subprocess.run(
        [sys.executable, "-m", "ldm", "keys", "show", str(path)],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()


def test_the_cluster_override_runs_three_nats_nodes_and_regional_workers_with_standbys(
    tmp_path: Path,
) -> None:
    """docker-compose.cluster.yml over docker-compose.yml: three NATS nodes whose config
    nats-server itself accepts (with the values compose gives each node), a service core
    and two regional workers with a standby each, all given every node, in place of
    broker-service, core-service and worker, which do not start; each command is one
    the CLI takes, and the core is limited like the other cores."""
    from laas.cli import build_parser
    from ldm.cli import _parser as build_ldm_parser
    from ldm.local.nats import find_nats_server

    services = load_compose(SETTINGS, CLUSTER)
    nodes = ["nats-1", "nats-2", "nats-3"]
    workers = ["worker-1of2", "worker-2of2", "worker-1of2-standby", "worker-2of2-standby"]
    cluster = {*nodes, "core-service-cluster", *workers}
    single = {"broker-service", "core-service", "worker"}  # what the cluster replaces
    base = {"broker-user", "broker-backbone", "core-user"}
    assert enabled(services) == base | cluster
    assert enabled(services, "bridges") == base | cluster | {"owntracks", "cam"}
    assert enabled(load_compose(SETTINGS)) == base | single  # without the override
    for name in enabled(services, "bridges"):
        assert set(services[name].get("depends_on", {})) <= enabled(services, "bridges"), name
    urls = "mqtt://nats-1:1883,nats-2:1883,nats-3:1883"
    core = services["core-service-cluster"]["command"]
    assert core[core.index("--cluster") + 1] == urls
    parsed = build_ldm_parser().parse_args(core[1:])
    mosquitto_core = build_ldm_parser().parse_args(services["core-service"]["command"][1:])
    for limit in ("grace", "idle_timeout", "rate", "burst", "rotation_period", "data_qos"):
        assert getattr(parsed, limit) == getattr(mosquitto_core, limit), limit
    # on NATS every hop waits about 10 s for the leaders a failed node's streams elect
    assert parsed.max_age == 10.0
    for name in workers:
        service = services[name]
        assert environment(service)["LAAS_CLUSTER"] == urls
        a = build_parser().parse_args(service["command"][1:])
        assert a.region == ("1/2" if "1of2" in name else "2/2")
        assert a.standby == name.endswith("-standby")
        assert a.identity is not None
        assert a.max_age == parsed.max_age
        health = service["healthcheck"]["test"]
        assert health[health.index("service") + 2] == f"laas-{name[7:11]}"
    need_nats()
    server = find_nats_server()
    assert server is not None
    config = ROOT / "deploy" / "nats" / "nats.conf"
    for name in nodes:
        service = services[name]
        assert mounts(service)["/etc/nats/nats.conf"] == config
        checked = subprocess.run(
            [server, "-c", str(config), "-t"],
            env={**os.environ, **environment(service)},
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert checked.returncode == 0, checked.stderr
        assert environment(service)["NATS_NAME"] == name


def test_compose_accounts_script_makes_the_keys_once(tmp_path: Path) -> None:
    first = make_accounts(tmp_path)
    keys = tmp_path / "keys"
    assert sorted(p.name for p in keys.iterdir()) == sorted(f"{k}.key" for k in KEY_FILES)
    pem = {name: (keys / f"{name}.key").read_bytes() for name in KEY_FILES}
    publics = {name: show_key(keys / f"{name}.key") for name in KEY_FILES}
    assert len(set(publics.values())) == 3, "one identity per service"
    for name, var in KEY_FILES.items():
        assert pem[name].startswith(b"-----BEGIN PRIVATE KEY-----"), name
        if var:
            assert first[var] == publics[name], name
        # the image's user may read its key, no other user of the host can
        info, shut = (keys / f"{name}.key").stat(), keys.stat().st_mode & 0o077 == 0
        if os.geteuid() == 0:
            assert (info.st_uid, info.st_mode & 0o777) == (image_uid(), 0o400), name
        else:
            assert info.st_mode & 0o777 == 0o644 and shut, name
    env_text = (tmp_path / ".env").read_text()
    assert not any(p.decode() in env_text for p in pem.values())
    # each value on its own line of env.example, under that line's comment
    example = (ROOT / "deploy" / "env.example").read_text()
    assert settings_lines(env_text) == settings_lines(example)
    # again: no key is overwritten and .env does not change
    assert make_accounts(tmp_path) == first
    assert {name: (keys / f"{name}.key").read_bytes() for name in KEY_FILES} == pem
    # a public key lost from .env (or stale after a key was replaced) follows the file;
    # its line stays where env.example puts it, under its comment
    (tmp_path / ".env").write_text(env_text.replace(first["LAAS_CORE_KEY"], "stale"))
    assert make_accounts(tmp_path) == first
    assert (tmp_path / ".env").read_text() == env_text
    assert {name: (keys / f"{name}.key").read_bytes() for name in KEY_FILES} == pem


def test_compose_accounts_script_makes_every_account_once(tmp_path: Path) -> None:
    first = make_accounts(tmp_path)
    for name in SECRETS:
        assert len(first[name]) == 24 and first[name].isalnum(), name
    hashes = (tmp_path / "passwd").read_text()
    users = [line.split(":")[0] for line in hashes.splitlines()]
    simulated = subprocess.run(
        [
            sys.executable,
            "-m",
            "laas.cli",
            "simulate",
            "--device-accounts",
            "--prefix",
            "sim-",
            "--list-accounts",
        ],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split()
    assert simulated == ["sim-car", "sim-cyclist-1", "sim-cyclist-2"]
    expected = ["ldm-core-user", "ldm-core-service", "laas-worker", "laas-health", *simulated]
    expected += ["laas-owntracks", "laas-cam"]  # the bridges (profile bridges)
    assert sorted(users) == sorted(expected)
    assert not any(first[name] in hashes for name in SECRETS)  # hashes only
    assert make_accounts(tmp_path) == first  # again: nothing changes
    assert (tmp_path / ".env").stat().st_mode & 0o077 == 0


# --- the services, run ---------------------------------------------------------------


class LocalCompose:
    """The compose services as processes on this machine."""

    def __init__(
        self, services: Mapping[str, Service], workdir: Path, secrets: Mapping[str, str]
    ) -> None:
        self.services = services
        self.workdir = workdir
        self.passwd = workdir / "passwd"  # compose mounts ./deploy/security/passwd
        self.keys = workdir / "keys"  # ... and the keys in ./deploy/security/keys/
        self.secrets = secrets
        self.ports = {name: free_port() for name, s in services.items() if is_broker(s)}
        self.metrics_ports: dict[str, int] = {}  # a Python service's, on this host
        self.processes: dict[str, subprocess.Popen[bytes]] = {}

    def host_file(self, path: Path) -> Path:
        """A mounted host file; the generated ones (passwd, keys) are this run's."""
        if path == PASSWD:
            return self.passwd
        if path.parent == KEYS:
            return self.keys / path.name
        if path.parent == HEALTH:
            return self.workdir / "health" / path.name
        return path

    def local(self, value: str, service: Service | None = None) -> str:
        """A value as seen from this machine: broker host names, mounted files (of a
        Python service: the processes see no container paths) and image paths mapped."""
        if service is not None and not is_broker(service):
            for target, host in mounts(service).items():
                value = value.replace(target, str(self.host_file(host)))
        for name, port in self.ports.items():
            value = value.replace(f"mqtt://{name}:1883", f"mqtt://127.0.0.1:{port}")
        return value.replace("/app/", f"{ROOT}/")

    def argv(self, command: list[str], service: Service | None = None) -> list[str]:
        program, *args = (self.local(str(c), service) for c in command)
        scripts = Path(sys.executable).parent
        if program in ("ldm", "laas"):
            script = scripts / program
            head = [str(script)] if script.exists() else [sys.executable, "-m", f"{program}.cli"]
        elif program == "python":
            head = [sys.executable]
        else:
            found = shutil.which(program) or shutil.which(program, path="/usr/sbin:/usr/bin")
            assert found, f"{program} is not installed here"
            head = [found]
        return head + args

    def env(self, service: Service) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith(("LAAS_", "LDM_"))}
        env.update({k: self.local(v, service) for k, v in environment(service).items()})
        name = next(n for n, s in self.services.items() if s is service)
        for prefix in ("LDM", "LAAS"):  # a metrics port per container in compose; here
            if f"{prefix}_METRICS_PORT" in env:  # all share this host: a free port each
                port = self.metrics_ports.setdefault(name, free_port())
                env[f"{prefix}_METRICS_PORT"] = str(port)
                env[f"{prefix}_METRICS_HOST"] = "127.0.0.1"
        env["PYTHONUNBUFFERED"] = "1"
        return env

    def start(self, name: str) -> None:
        service = self.services[name]
        if is_broker(service):
            config = mounted_config(service).read_text()
            port = self.ports[name]
            local, n = re.subn(r"(?m)^listener 1883\s*$", f"listener {port} 127.0.0.1", config)
            assert n == 1, f"{name}: expected one `listener 1883` line"
            for in_image, mounted in mounts(service).items():
                host = self.host_file(mounted)  # passwd: made for this run, as deployed
                if host == mounted and host.is_file():
                    # The same file, copied where mosquitto (which drops root to user
                    # "mosquitto") can read it whatever the checkout's permissions.
                    copy = self.workdir / f"{name}-{host.name}"
                    shutil.copyfile(host, copy)
                    copy.chmod(0o644)
                    host = copy
                local = re.sub(rf"(?m)^(\w+) {re.escape(in_image)}\s*$", rf"\1 {host}", local)
            path = self.workdir / f"{name}.conf"
            path.write_text(local)
            path.chmod(0o644)
            binary = find_mosquitto()
            assert binary is not None
            argv = [binary, "-c", str(path)]
            env = dict(os.environ)
        else:
            for host in mounts(service).values():
                assert self.host_file(host).exists(), f"{name}: nothing to mount at {host}"
            argv = self.argv(service["command"], service)
            env = self.env(service)
        log = open(self.workdir / f"{name}.log", "wb")  # noqa: SIM115
        self.processes[name] = subprocess.Popen(
            argv, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=self.workdir
        )
        log.close()

    def healthcheck(self, name: str) -> subprocess.CompletedProcess[bytes]:
        test = self.services[name]["healthcheck"]["test"]
        assert test[0] == "CMD", f"{name}: health check in exec form"
        argv = self.argv(test[1:], self.services[name])
        if is_broker(self.services[name]):
            if not Path(argv[0]).name.startswith("mosquitto_"):
                raise AssertionError(f"{name}: unknown broker check {argv}")
            argv += ["-h", "127.0.0.1", "-p", str(self.ports[name])]
        env = self.env(self.services[name])
        if "XDG_CONFIG_HOME" in env:  # a mounted directory of option files: the host's
            for target, host in mounts(self.services[name]).items():
                if str(Path(target).parent) == env["XDG_CONFIG_HOME"]:
                    env["XDG_CONFIG_HOME"] = str(self.host_file(host).parent)
        return subprocess.run(argv, env=env, capture_output=True)

    def wait_healthy(self, name: str, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while True:
            process = self.processes[name]
            assert process.poll() is None, f"{name} exited:\n{self.log(name)}"
            result = self.healthcheck(name)
            if result.returncode == 0:
                return
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"{name} not healthy within {timeout} s: {result.stdout!r} "
                    f"{result.stderr!r}\n{self.log(name)}"
                )
            time.sleep(0.2)

    def log(self, name: str) -> str:
        path = self.workdir / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def stop(self, name: str) -> int:
        process = self.processes.pop(name)
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(5)
        return process.returncode

    def stop_all(self) -> None:
        for name in reversed(list(self.processes)):
            self.stop(name)


OWN_MAP = "my-area.geojson"  # an operator's map, in LAAS_MAPS_DIR


@pytest.fixture
def local_compose() -> Iterator[LocalCompose]:
    need_mosquitto()
    workdir = Path(tempfile.mkdtemp(prefix="laas-compose-"))
    workdir.chmod(0o755)  # mosquitto started as root reads its config as "mosquitto"
    # deploy/security/compose-accounts.sh, then what `LAAS_SIM_SPEEDUP=25 docker compose
    # --profile sim up` would substitute from the .env it wrote
    secrets = make_accounts(workdir)
    # ... with the operator's own map in the maps folder, served without a rebuild
    # (LAAS_MAPS_DIR mounted at /srv/laas/maps): the Hamburg map under another name
    maps = workdir / "my-maps"
    maps.mkdir()
    shutil.copyfile(ROOT / "maps" / "messe-hamburg.geojson", maps / OWN_MAP)
    env = {
        **secrets,
        "LAAS_SIM_SPEEDUP": "25",
        "LAAS_MAPS_DIR": str(maps),
        "LAAS_MAP": f"/srv/laas/maps/{OWN_MAP}",
    }
    deployment = LocalCompose(load_compose(env), workdir, secrets)
    try:
        yield deployment
    finally:
        deployment.stop_all()
        shutil.rmtree(workdir, ignore_errors=True)


@pytest.mark.mosquitto
@pytest.mark.timeout(120)
def test_compose_services_serve_the_simulator(local_compose: LocalCompose) -> None:
    services = local_compose.services
    running = [n for n in start_order(services) if not services[n].get("profiles")]
    assert running[-1] == "worker" and all(is_broker(services[n]) for n in running[:3])
    keys = {p.name: p.read_bytes() for p in local_compose.keys.iterdir()}
    for name in running:
        local_compose.start(name)
        local_compose.wait_healthy(name)
    # the brokers are locked: no anonymous client, no wrong password, no $SYS for others
    for name in running[:3]:
        port = str(local_compose.ports[name])
        sub = [*local_compose.argv(["mosquitto_sub"]), "-h", "127.0.0.1", "-p", port]
        for who in ([], ["-u", "laas-health", "-P", "wrong"]):
            check = [*sub, *who, "-t", "$SYS/broker/version", "-C", "1", "-W", "2"]
            assert subprocess.run(check, capture_output=True).returncode != 0, (name, who)
        car = ["-u", "sim-car", "-P", local_compose.secrets["LAAS_SIM_PASSWORD"]]
        check = [*sub, *car, "-t", "$SYS/broker/version", "-C", "1", "-W", "2"]
        assert subprocess.run(check, capture_output=True).returncode != 0, name

    sim = services["simulator"]
    for dep in sim["depends_on"]:
        assert local_compose.healthcheck(dep).returncode == 0, dep
    # the simulator pins the worker's and the user core's keys: it takes no other service
    # and acts on no notice another key signed, so its answers prove the whole chain
    sim_env = local_compose.env(sim)
    for var in ("LAAS_SERVICE_KEY", "LAAS_CORE_KEY"):
        assert sim_env[var] == local_compose.secrets[var] != "", var
    result = subprocess.run(
        local_compose.argv(sim["command"], sim),
        env=sim_env,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=local_compose.workdir,
    )
    assert result.returncode == 0, result.stderr + local_compose.log("worker")
    summary = re.search(r"(\d+)/(\d+) answered; lane accuracy ([0-9.]+)", result.stderr)
    assert summary, result.stderr
    answered, total, accuracy = int(summary[1]), int(summary[2]), float(summary[3])
    assert total == 303 and answered == total, result.stderr
    assert accuracy > 0.9, result.stderr
    assert len(result.stdout.splitlines()) == total
    # each service signed with the key compose-accounts.sh made for it (none made its
    # own), and the cores dropped no announcement of laas
    public = {name: show_key(local_compose.keys / f"{name}.key") for name in KEY_FILES}
    assert public["laas-worker"] == local_compose.secrets["LAAS_SERVICE_KEY"]
    assert public["core-user"] == local_compose.secrets["LAAS_CORE_KEY"]
    worker = local_compose.log("worker")
    assert f"identity (participants pin it): {public['laas-worker']}" in worker, worker
    # it served the operator's map from the maps folder
    assert f"of {local_compose.workdir / 'my-maps' / OWN_MAP} " in worker, worker
    for name in ("user", "service"):
        log = local_compose.log(f"core-{name}")
        assert f"its key (participants pin it): {public[f'core-{name}']}" in log, log
        assert "dropped" not in log, log
    assert {p.name: p.read_bytes() for p in local_compose.keys.iterdir()} == keys

    # the worker's health check is not vacuous: stopping it withdraws the service
    assert local_compose.stop("worker") == 0
    assert f"{total} answered" in local_compose.log("worker")
    assert local_compose.healthcheck("worker").returncode == 1


@pytest.mark.mosquitto
@pytest.mark.timeout(150)
def test_compose_bridges_serve_cam_stations_and_phones_under_the_shipped_acl(
    local_compose: LocalCompose,
) -> None:
    """Profile `bridges` on the shipped ACL: a CAM station (its account its source_uuid)
    gets every CAM answered and reads no other station's answers; an OwnTracks phone
    gets its lane; each bridge logs its devices in as their own accounts. A CAM dated
    20 minutes back is refused for its clock, and the worker's stop summary says so."""
    from laas.map.bundled import bundled_map
    from laas.map.geojson import read_geojson_file
    from laas.sim.scenario import ErrorModel, hamburg_scenario, simulate
    from ldm import BrokerSettings
    from ldm.transport import Event, Message, Transport
    from tests.bridges.test_live import cam_message, now_shifted
    from tests.bridges.test_owntracks_acl import owntracks_location

    services = local_compose.services
    device = local_compose.secrets["LAAS_DEVICE_PASSWORD"]
    station, other, station_id = "its-car-1", "its-car-2", 4242
    own = {station: "station-pw", other: "other-pw", "alice": "alice-pw"}
    lines = [f"{u}={pw}" for u, pw in own.items()]
    lines += [f"cam.{station}.{station_id}={device}", f"ot.alice.phone={device}"]
    subprocess.run(  # docs/bridges.md, "Accounts": before broker-user starts
        ["bash", str(ACCOUNTS.parent / "make-passwd.sh"), str(local_compose.passwd), "-"],
        input="\n".join(lines) + "\n", text=True, check=True, capture_output=True,
        env={"PATH": "/usr/bin:/bin", "MODE": "0644"},
    )  # fmt: skip
    running = [n for n in start_order(services) if not services[n].get("profiles")]
    bridges = [n for n, s in services.items() if s.get("profiles") == ["bridges"]]
    assert sorted(bridges) == ["cam", "owntracks"]
    for name in running + bridges:
        local_compose.start(name)
        local_compose.wait_healthy(name)
    url = f"mqtt://127.0.0.1:{local_compose.ports['broker-user']}"
    inboxes: dict[str, list[Message]] = {u: [] for u in own}

    def connect(user: str, *subscriptions: str) -> Transport:
        def sink(e: Event) -> None:
            if isinstance(e, Message):
                inboxes[user].append(e)

        account = BrokerSettings(url=url, username=user, password=own[user])
        t = Transport(account, client_id=user, sink=sink, name=user)
        for topic in subscriptions:
            t.subscribe(topic, 1)
        t.start(timeout=5)
        return t

    hdmap = read_geojson_file(bundled_map("messe-hamburg"))
    trace = simulate(hdmap, hamburg_scenario(), ErrorModel(), 0)
    car = now_shifted([f.measurement for f in trace.fixes if f.user == "car"][:20], 20.0)
    car_station = connect(station, "laas/cam/#")  # the ACL lets it read laas/cam/its-car-1
    snoop = connect(other, "laas/cam/#", "owntracks/#")  # ... and this one nothing of it
    phone = connect("alice", "owntracks/+/+")
    try:
        old = cam_message(car[0], 0, station, station_id)
        old["timestamp"] -= 20 * 60 * 1000  # 20 minutes back: refused for its clock
        car_station.publish(f"v2x/cam/{station}/cam", json.dumps(old).encode(), 1, False)
        for i, fix in enumerate(car[1:], 1):
            cam = cam_message(fix, i, station, station_id)
            car_station.publish(f"v2x/cam/{station}/cam", json.dumps(cam).encode(), 1, False)
            location = owntracks_location(fix, fix.timestamp // 1000)
            phone.publish("owntracks/alice/phone", json.dumps(location).encode(), 1, False)
            time.sleep(0.1)

        def answers(user: str, topic: str) -> list[dict[str, Any]]:
            return [json.loads(m.payload) for m in inboxes[user] if m.topic == topic]

        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and (
            len(answers(station, f"laas/cam/{station}")) < len(car) - 1
            or not answers("alice", "owntracks/alice/phone-lane")
        ):
            time.sleep(0.2)
    finally:
        for t in (car_station, snoop, phone):
            t.stop()
    cams = answers(station, f"laas/cam/{station}")
    assert len(cams) == len(car) - 1, local_compose.log("cam")
    lanes = [c["message"]["high_frequency_container"].get("lane_position") for c in cams]
    assert all(isinstance(n, int) and n >= 1 for n in lanes), lanes
    ellipse = cams[-1]["message"]["basic_container"]["reference_position"]
    axes = ellipse["position_confidence_ellipse"]
    assert axes["semi_major_confidence"] > axes["semi_minor_confidence"], axes
    assert answers("alice", "owntracks/alice/phone-lane"), local_compose.log("owntracks")
    assert inboxes[other] == []  # no other station's answers, no phone's positions
    for name in bridges:
        assert local_compose.stop(name) == 0, local_compose.log(name)
    assert local_compose.stop("worker") == 0
    summary = re.search(
        r"stopped; (\d+) answered, 1 refused \(1 clock\)", local_compose.log("worker")
    )
    assert summary and int(summary[1]) >= len(car), local_compose.log("worker")
    assert "laas cam: stopped; 1 devices opened" in local_compose.log("cam")
    # Mosquitto's own words at start: no deprecated option, no warning
    for name in ("broker-user", "broker-backbone", "broker-service"):
        log = local_compose.log(name)
        assert "message_size_limit" not in log, log
        warnings = [line for line in log.splitlines() if "Warning" in line or "Note" in line]
        assert warnings == [], warnings


def test_the_brokers_run_the_mosquitto_series_the_tests_run() -> None:
    """The image is pinned to a 2.0 release (2.1 deprecates password_file and acl_file),
    the series of the mosquitto these tests start."""
    services = load_compose(SETTINGS)
    images = {s["image"] for s in services.values() if "mosquitto" in str(s.get("image"))}
    assert images == {MOSQUITTO_IMAGE}
    tag = MOSQUITTO_IMAGE.split(":", 1)[1]
    assert re.fullmatch(r"2\.0\.\d+", tag), f"pin a 2.0.x release, not {tag!r}"
    binary = find_mosquitto()
    if binary is None:
        pytest.skip("mosquitto is not installed: the series it runs cannot be compared")
    help_text = subprocess.run([binary, "-h"], capture_output=True, text=True).stdout
    found = re.search(r"mosquitto version (\d+\.\d+)\.\d+", help_text)
    assert found and found[1] == "2.0", help_text[:80]


def test_env_example_gives_the_defaults_of_the_compose_files() -> None:
    """Each non-secret value of deploy/env.example is the default every compose file
    (docker-compose.yml and its overrides) uses for it when unset, and each is used."""
    example = dict(
        line.split("=", 1)
        for line in (ROOT / "deploy" / "env.example").read_text().splitlines()
        if line and not line.startswith("#")
    )
    texts = "".join(path.read_text() for path in (COMPOSE, CLUSTER, TLS))
    used = {m[0]: m[1] for m in re.findall(r"\$\{(\w+):-([^}]*)\}", texts)}
    for name, value in example.items():
        if not value:  # secrets and keys: compose-accounts.sh fills them in
            continue
        assert name in used, f"{name} of env.example is used by no compose file"
        defaults = set(re.findall(rf"\$\{{{name}:-([^}}]*)\}}", texts))
        assert defaults == {value}, (name, defaults, value)
