"""Adding participants' accounts as the docs say, checked against a real Mosquitto that
reads the password file as the eclipse-mosquitto image does (uid 1883): adding a phone
never changes another account, and the file is readable by the broker whether root or
another user wrote it, without MODE set."""

from __future__ import annotations

import os
import stat
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pydantic
import pytest

import ldm
from ldm import LdmError
from ldm.cli import main
from ldm.config import BrokerSettings
from ldm.local.brokers import MosquittoBroker
from ldm.local.pytest_plugin import need_mosquitto
from ldm.ops.passwd import verify
from ldm.transport import Transport

ROOT = Path(__file__).resolve().parent.parent
SECURITY = ROOT / "deploy" / "security"
MOSQUITTO_UID = 1883  # the user eclipse-mosquitto runs as
OTHER_UID = 65534  # a host user who is not root (nobody)


LDM_PATHS = [Path(ldm.__file__).parent.parent, Path(pydantic.__file__).parent.parent]
"""Where this checkout's ldm and its dependencies lie (the PYTHONPATH of `ldm_for`)."""


@pytest.fixture
def reach() -> Iterator[Callable[[Path], None]]:
    """Let another user pass through the folders above a path (o+x where it is missing:
    a checkout in a folder of mode 0700, as `mktemp -d` makes, is closed to it), each put
    back as it was afterwards. Nothing is made readable that was not."""
    changed: list[tuple[Path, int]] = []

    def grant(path: Path) -> None:
        for folder in [path, *path.parents]:
            mode = folder.stat().st_mode
            if folder.is_dir() and not mode & stat.S_IXOTH:
                changed.append((folder, stat.S_IMODE(mode)))
                folder.chmod(stat.S_IMODE(mode) | stat.S_IXOTH)

    yield grant
    for folder, mode in reversed(changed):
        folder.chmod(mode)


def ldm_for(uid: int, directory: Path) -> Path:
    """A directory with an `ldm` command that user `uid` can run: this checkout's ldm on
    the system's python3 (the test's own interpreter may lie where only root can reach)."""
    python = Path("/usr/bin/python3")
    if not python.exists():
        pytest.skip("needs /usr/bin/python3 to run ldm as another user")
    paths = LDM_PATHS
    bin_dir = directory / "bin"
    bin_dir.mkdir(mode=0o755)
    command = bin_dir / "ldm"
    command.write_text(
        f'#!/bin/sh\nPYTHONPATH={":".join(map(str, paths))} exec {python} -m ldm "$@"\n'
    )
    command.chmod(0o755)
    return bin_dir


def script(
    name: str, *args: str, stdin: str = "", uid: int | None = None, **env: str
) -> subprocess.CompletedProcess[str]:
    """Run deploy/security/`name` as an operator would (as `uid`, root if None)."""
    path = "/usr/bin:/bin:/usr/sbin"
    if uid is not None:
        path = f"{env.pop('LDM_BIN')}:{path}"
    return subprocess.run(
        ["bash", str(SECURITY / name), *args],
        input=stdin,
        capture_output=True,
        text=True,
        check=True,
        env={"PATH": path, **env},
        user=uid,
        group=uid,
        extra_groups=None if uid is None else [],
    )


def can_connect(url: str, user: str, password: str) -> bool:
    settings = BrokerSettings(url=url, username=user, password=password)
    transport = Transport(settings, client_id=user, sink=lambda e: None)
    try:
        transport.start(timeout=3)
    except LdmError:
        return False
    transport.stop()
    return True


@pytest.mark.mosquitto
@pytest.mark.timeout(120)
@pytest.mark.parametrize("writer", ["root", "a non-root user"])
def test_adding_a_phone_keeps_every_other_account_and_the_broker_reads_the_file(
    writer: str, reach: Callable[[Path], None]
) -> None:
    need_mosquitto()
    if os.geteuid() != 0:
        pytest.skip("runs the scripts as root and as another user: run the tests as root")
    uid = None if writer == "root" else OTHER_UID
    broker = MosquittoBroker(allow_anonymous=False, run_as=MOSQUITTO_UID)
    work = broker.directory / "deployment"
    work.mkdir(mode=0o755)
    if uid is not None:
        os.chown(work, uid, uid)
    passwd = work / "passwd"
    tools = {} if uid is None else {"LDM_BIN": str(ldm_for(uid, broker.directory))}
    if uid is not None:  # the scripts and ldm of this checkout, wherever it was cloned
        for path in (SECURITY, *LDM_PATHS):
            reach(path)
    # the deployment's accounts, as the compose steps make them (no MODE given)
    script(
        "compose-accounts.sh",
        str(work / ".env"),
        uid=uid,
        PASSWD_FILE=str(passwd),
        KEYS_DIR=str(work / "keys"),
        HEALTH_DIR=str(work / "health"),
        **tools,
    )
    env = dict(
        line.split("=", 1)
        for line in (work / ".env").read_text().splitlines()
        if line and not line.startswith("#")
    )
    # the phone steps: the phone's account (naming the bridge's too), then its device's
    added = script("make-passwd.sh", str(passwd), "alice", "laas-owntracks", uid=uid, **tools)
    (printed,) = added.stdout.splitlines()  # only the new account's password
    assert printed.startswith("alice=")
    assert "laas-owntracks is already in" in added.stderr and "kept" in added.stderr
    device = script(
        "make-passwd.sh", str(passwd), "-", stdin="ot.alice.phone=device-pw\n", uid=uid, **tools
    )
    # the script says what it made of the file, and the broker's user can read it
    mode = passwd.stat().st_mode & 0o777
    if uid is None:
        assert (passwd.stat().st_uid, mode) == (MOSQUITTO_UID, 0o640)
        assert "mode 0640, owned by 1883:1883" in device.stderr
    else:
        assert (passwd.stat().st_uid, mode) == (OTHER_UID, 0o644)
        assert "mode 0644" in device.stderr
    broker.config_file.write_text(broker.config_file.read_text() + f"password_file {passwd}\n")
    with broker:  # mosquitto runs as uid 1883 and reads the file at start
        url = broker.url
        assert can_connect(url, "laas-owntracks", env["LAAS_OWNTRACKS_PASSWORD"])
        assert can_connect(url, "laas-cam", env["LAAS_CAM_PASSWORD"])
        assert can_connect(url, "alice", printed.split("=", 1)[1])
        assert can_connect(url, "ot.alice.phone", "device-pw")
        assert not can_connect(url, "laas-owntracks", "device-pw")


def test_ldm_passwd_changes_an_existing_account_only_with_replace(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "passwd"
    assert main(["passwd", str(path), "bridge=old-pw"]) == 0
    assert main(["passwd", str(path), "bridge=new-pw", "car"]) == 0
    captured = capsys.readouterr()
    assert [line.split("=")[0] for line in captured.out.splitlines()] == ["car"]
    assert "bridge is already in" in captured.err and "--replace" in captured.err
    lines = {line.split(":")[0]: line for line in path.read_text().splitlines()}
    assert verify(lines["bridge"], "old-pw")
    assert main(["passwd", "--replace", str(path), "bridge=new-pw"]) == 0
    lines = {line.split(":")[0]: line for line in path.read_text().splitlines()}
    assert verify(lines["bridge"], "new-pw") and sorted(lines) == ["bridge", "car"]
