"""docker-compose.yml, run without Docker: every service as a local process.

There is no container engine on the test machines, so this test reads the compose file
and starts each service with the same command, arguments and environment as compose
would: the brokers as Mosquitto processes with the mounted config (only the listener
port changes: a free port per broker), the Python services through the same console
scripts. Service host names (`broker-user`, ...) become 127.0.0.1:<that broker's
port>, and image paths under /app/ become the repository's. Dependencies start in
compose's order and wait for the compose health checks, which run here too. Then the
simulator (profile `sim`) drives the Hamburg road users through the deployment.
"""

from __future__ import annotations

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

from ldm.pytest_plugin import need_mosquitto
from ldm.testing import find_mosquitto, free_port

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
MOSQUITTO_IMAGE = "eclipse-mosquitto:2"
CONFIG_IN_IMAGE = "/mosquitto/config/mosquitto.conf"
_VARIABLE = re.compile(r"\$\$|\$\{(\w+)(?:(:?-)([^}]*))?\}|\$(\w+)")

Service = dict[str, Any]


def interpolate(value: Any, env: Mapping[str, str]) -> Any:
    """Compose's variable substitution: ${X}, ${X:-default}, ${X-default}, $X and $$."""
    if isinstance(value, str):

        def sub(m: re.Match[str]) -> str:
            if m.group(0) == "$$":
                return "$"
            name = m.group(1) or m.group(4)
            if m.group(2) == ":-":
                return env.get(name) or m.group(3)
            if m.group(2) == "-":
                return env.get(name, m.group(3))
            return env.get(name, "")

        return _VARIABLE.sub(sub, value)
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    return value


def load_compose(env: Mapping[str, str] | None = None) -> dict[str, Service]:
    """The services of docker-compose.yml, with variables substituted from `env`."""
    data = yaml.safe_load(COMPOSE.read_text())
    services: dict[str, Service] = interpolate(data["services"], env or {})
    return services


def is_broker(service: Service) -> bool:
    return bool(service.get("image") == MOSQUITTO_IMAGE)


def mounted_config(service: Service) -> Path:
    """The host file a broker service mounts as its mosquitto.conf."""
    for volume in service.get("volumes", []):
        source, target, *_ = str(volume).split(":")
        if target == CONFIG_IN_IMAGE:
            return (ROOT / source).resolve()
    raise AssertionError(f"broker mounts no {CONFIG_IN_IMAGE}: {service.get('volumes')}")


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
    services = load_compose()
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


def test_every_mosquitto_config_in_use_is_tuned() -> None:
    services = load_compose()
    configs = {mounted_config(s) for s in services.values() if is_broker(s)}
    assert configs, "no broker mounts a config"
    for config in configs:
        lines = {line.split("#")[0].strip() for line in config.read_text().splitlines()}
        assert "set_tcp_nodelay true" in lines, config
        assert "listener 1883" in lines, config
        assert "persistence false" in lines or "persistence true" in lines, config
        assert "allow_anonymous true" in lines, config  # until the access-control issue


def test_cores_and_worker_match_the_topology() -> None:
    services = load_compose()
    for name in ("user", "service"):
        command = services[f"core-{name}"]["command"]
        assert command[:4] == ["ldm", "core", "--name", name]
        assert command[command.index("--cluster") + 1] == f"mqtt://broker-{name}:1883"
        assert command[command.index("--backbone") + 1] == "mqtt://broker-backbone:1883"
        assert command[command.index("--rotation-period") + 1] == "120"
    worker = services["worker"]
    assert worker["command"][:2] == ["laas", "worker"]
    assert environment(worker)["LAAS_CLUSTER"] == "mqtt://broker-service:1883"
    sim = services["simulator"]["command"]
    assert sim[:2] == ["laas", "simulate"]
    assert sim[sim.index("--cluster") + 1] == "mqtt://broker-user:1883"
    # configuration by environment
    changed = load_compose({"LDM_ROTATION_PERIOD": "30", "LAAS_LOG_LEVEL": "debug"})
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


def test_interpolation_follows_compose() -> None:
    env = {"A": "1", "E": ""}
    assert interpolate("${A:-x} ${B:-x} ${E:-x} ${E-x} ${B-y} $A $$SYS", env) == "1 x x  y 1 $SYS"


# --- the services, run ---------------------------------------------------------------


class LocalCompose:
    """The compose services as processes on this machine."""

    def __init__(self, services: Mapping[str, Service], workdir: Path) -> None:
        self.services = services
        self.workdir = workdir
        self.ports = {name: free_port() for name, s in services.items() if is_broker(s)}
        self.processes: dict[str, subprocess.Popen[bytes]] = {}

    def local(self, value: str) -> str:
        """A value as seen from this machine: broker host names and image paths mapped."""
        for name, port in self.ports.items():
            value = value.replace(f"mqtt://{name}:1883", f"mqtt://127.0.0.1:{port}")
        return value.replace("/app/", f"{ROOT}/")

    def argv(self, command: list[str]) -> list[str]:
        program, *args = (self.local(str(c)) for c in command)
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
        env = {k: v for k, v in os.environ.items() if not k.startswith("LAAS_")}
        env.update({k: self.local(v) for k, v in environment(service).items()})
        env["PYTHONUNBUFFERED"] = "1"
        return env

    def start(self, name: str) -> None:
        service = self.services[name]
        if is_broker(service):
            config = mounted_config(service).read_text()
            port = self.ports[name]
            local, n = re.subn(r"(?m)^listener 1883\s*$", f"listener {port} 127.0.0.1", config)
            assert n == 1, f"{name}: expected one `listener 1883` line"
            path = self.workdir / f"{name}.conf"
            path.write_text(local)
            path.chmod(0o644)
            binary = find_mosquitto()
            assert binary is not None
            argv = [binary, "-c", str(path)]
            env = dict(os.environ)
        else:
            argv = self.argv(service["command"])
            env = self.env(service)
        log = open(self.workdir / f"{name}.log", "wb")  # noqa: SIM115
        self.processes[name] = subprocess.Popen(
            argv, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=self.workdir
        )
        log.close()

    def healthcheck(self, name: str) -> subprocess.CompletedProcess[bytes]:
        test = self.services[name]["healthcheck"]["test"]
        assert test[0] == "CMD", f"{name}: health check in exec form"
        argv = self.argv(test[1:])
        if is_broker(self.services[name]):
            if not Path(argv[0]).name.startswith("mosquitto_"):
                raise AssertionError(f"{name}: unknown broker check {argv}")
            argv += ["-h", "127.0.0.1", "-p", str(self.ports[name])]
        return subprocess.run(argv, env=self.env(self.services[name]), capture_output=True)

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


@pytest.fixture
def local_compose() -> Iterator[LocalCompose]:
    need_mosquitto()
    workdir = Path(tempfile.mkdtemp(prefix="laas-compose-"))
    workdir.chmod(0o755)  # mosquitto started as root reads its config as "mosquitto"
    # what `LAAS_SIM_SPEEDUP=25 docker compose --profile sim up` would substitute
    deployment = LocalCompose(load_compose({"LAAS_SIM_SPEEDUP": "25"}), workdir)
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
    for name in running:
        local_compose.start(name)
        local_compose.wait_healthy(name)

    sim = services["simulator"]
    for dep in sim["depends_on"]:
        assert local_compose.healthcheck(dep).returncode == 0, dep
    result = subprocess.run(
        local_compose.argv(sim["command"]),
        env=local_compose.env(sim),
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

    # the worker's health check is not vacuous: stopping it withdraws the service
    assert local_compose.stop("worker") == 0
    assert f"{total} answered" in local_compose.log("worker")
    assert local_compose.healthcheck("worker").returncode == 1
