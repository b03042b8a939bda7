"""Mosquitto password files from `ldm.passwd` and `ldm passwd`, checked against Mosquitto."""

from __future__ import annotations

import base64
import hashlib
import io
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from ldm.cli import main
from ldm.config import BrokerSettings
from ldm.errors import LdmError, PasswordFileError
from ldm.local.brokers import MosquittoBroker, find_mosquitto, mosquitto_required
from ldm.local.pytest_plugin import need_mosquitto
from ldm.ops.passwd import check_user, hash_password, password_line, set_passwords, verify
from ldm.transport.mqtt import Transport

ROOT = Path(__file__).resolve().parents[2]
MAKE_PASSWD = ROOT / "deploy" / "security" / "make-passwd.sh"
# Written by mosquitto_passwd 2.0.11 (`mosquitto_passwd -c -b f user pw`).
MOSQUITTO_LINE = (
    "user:$7$101$lsfNnXrbltEBNcqM$htAlOQ4uzfakaGSSLVU2/bQ3BoQ1HHAVNVjBcwVW9ATHrYLbMUTfVK39f"
    "mmUvXuZeYLO41YdQqmPQ6s/O3v1EQ=="
)
BAD_USERS = ["", "a:b", "a\nb", "a\rb", "a\tb", "a\x00b", " a", "a ", "#a", "x" * 65536]


def test_a_hash_is_mosquittos_pbkdf2_line() -> None:
    field = MOSQUITTO_LINE.split(":", 1)[1]
    salt = base64.b64decode(field.split("$")[3])
    assert hash_password("pw", salt=salt) == field
    assert verify(MOSQUITTO_LINE, "pw")
    assert not verify(MOSQUITTO_LINE, "pW")
    assert not verify(MOSQUITTO_LINE, "pw ")


def test_hash_and_verify_round_trip() -> None:
    for password in ("s3cret", "pässwörd", "a:b=c$d", "x" * 1000):
        line = password_line("car-17", password)
        user, _, field = line.partition(":")
        _, kind, iterations, salt, key = field.split("$")
        assert (user, kind, iterations) == ("car-17", "7", "101")
        assert len(base64.b64decode(salt)) == 12 and len(base64.b64decode(key)) == 64
        assert verify(line, password)
        assert not verify(line, password + "x")
    # a fresh salt each time
    assert password_line("a", "pw") != password_line("a", "pw")


def test_verify_reads_the_older_sha512_lines() -> None:
    salt = b"0123456789ab"
    key = hashlib.sha512(b"pw" + salt).digest()
    line = f"old:$6${base64.b64encode(salt).decode()}${base64.b64encode(key).decode()}"
    assert verify(line, "pw") and not verify(line, "px")


@pytest.mark.parametrize(
    "line",
    ["no colon", "u:plain", "u:$7$x$c2FsdA==$a2V5", "u:$7$0$c2FsdA==$a2V5", "u:$7$101$!!$a2V5"],
)
def test_a_malformed_line_is_an_error_not_a_mismatch(line: str) -> None:
    with pytest.raises(PasswordFileError, match="malformed password line"):
        verify(line, "pw")


@pytest.mark.parametrize("user", BAD_USERS)
def test_bad_user_names_are_refused(tmp_path: Path, user: str) -> None:
    with pytest.raises(PasswordFileError, match="bad user name") as caught:
        check_user(user)
    assert isinstance(caught.value, LdmError)
    path = tmp_path / "passwd"
    with pytest.raises(PasswordFileError):
        set_passwords(path, {"good": "pw", user: "pw"})
    assert not path.exists()  # nothing is written when one entry is bad


def test_an_empty_password_is_refused(tmp_path: Path) -> None:
    with pytest.raises(PasswordFileError, match="empty password"):
        set_passwords(tmp_path / "passwd", {"car": ""})


def test_the_file_is_extended_not_clobbered(tmp_path: Path) -> None:
    path = tmp_path / "passwd"
    path.write_text(f"# participants\n{MOSQUITTO_LINE}\nbike:$7$old\nbike:$7$older\n")
    path.chmod(0o600)
    set_passwords(path, {"bike": "b1", "car": "c1"}, mode=0o640)
    lines = path.read_text().splitlines()
    assert lines[:2] == ["# participants", MOSQUITTO_LINE]
    assert [line.split(":")[0] for line in lines] == ["# participants", "user", "bike", "car"]
    assert verify(lines[2], "b1") and verify(lines[3], "c1")
    assert path.stat().st_mode & 0o7777 == 0o640
    set_passwords(path, {"car": "c2"}, mode=0o644)
    after = path.read_text().splitlines()
    assert after[:3] == lines[:3] and verify(after[3], "c2") and not verify(after[3], "c1")
    assert path.stat().st_mode & 0o7777 == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == ["passwd"]  # no temporary left


def test_a_failed_write_leaves_the_old_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "passwd"
    path.write_text(MOSQUITTO_LINE + "\n")

    def full_disk(*_args: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full_disk)
    with pytest.raises(OSError, match="No space"):
        set_passwords(path, {"car": "c"})
    assert path.read_text() == MOSQUITTO_LINE + "\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["passwd"]


def test_the_cli_prints_only_generated_passwords(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "passwd"
    monkeypatch.setattr(sys, "stdin", io.StringIO("carol=c=3\n\ndave\n"))
    assert main(["passwd", str(path), "alice", "bob=b0b-pw", "-", "--mode", "0600"]) == 0
    out = capsys.readouterr().out.splitlines()
    generated = dict(line.split("=", 1) for line in out)
    assert sorted(generated) == ["alice", "dave"]
    assert all(len(p) == 24 for p in generated.values())
    lines = {line.split(":")[0]: line for line in path.read_text().splitlines()}
    passwords = {**generated, "bob": "b0b-pw", "carol": "c=3"}
    assert sorted(lines) == sorted(passwords)
    assert all(verify(lines[u], pw) for u, pw in passwords.items())
    assert not any(pw in path.read_text() for pw in [*generated.values(), "b0b-pw"])
    assert path.stat().st_mode & 0o7777 == 0o600

    before = path.read_text()
    for bad in (["a:b=1"], ["bob=1", "bob=2"], ["eve="]):
        assert main(["passwd", str(path), *bad]) == 2
        captured = capsys.readouterr()
        assert captured.out == "" and captured.err.startswith("ldm passwd: ")
    assert path.read_text() == before


def test_make_passwd_script_needs_no_mosquitto(tmp_path: Path) -> None:
    path = tmp_path / "passwd"
    env = {"PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin"}
    result = subprocess.run(
        ["bash", str(MAKE_PASSWD), str(path), "car-17", "bike-42=b"],
        capture_output=True,
        text=True,
        env={**env, "MOSQUITTO_PASSWD": "/nonexistent"},
    )
    assert result.returncode == 0, result.stderr
    (car,) = result.stdout.splitlines()
    assert car.startswith("car-17=")
    lines = path.read_text().splitlines()
    assert verify(lines[0], car.split("=", 1)[1]) and verify(lines[1], "b")
    assert path.stat().st_mode & 0o7777 == 0o640
    bad = subprocess.run(["bash", str(MAKE_PASSWD), str(path), "a:b"], env=env)
    assert bad.returncode == 2


# --- against Mosquitto ---------------------------------------------------------------


def mosquitto_passwd() -> str:
    """The mosquitto_passwd binary beside mosquitto; skips or fails like need_mosquitto."""
    need_mosquitto()
    mosquitto = find_mosquitto()
    assert mosquitto is not None
    path = os.pathsep.join([os.environ.get("PATH", ""), str(Path(mosquitto).parent), "/usr/bin"])
    found = shutil.which("mosquitto_passwd", path=path)
    if found is None:
        message = "mosquitto_passwd is not installed (apt-get install mosquitto)"
        if mosquitto_required():
            pytest.fail(f"LDM_REQUIRE_MOSQUITTO=1 but {message}")
        pytest.skip(message)
    return found


@pytest.mark.mosquitto
def test_verify_accepts_what_mosquitto_passwd_writes(tmp_path: Path) -> None:
    binary = mosquitto_passwd()
    path = tmp_path / "passwd"
    passwords = {"car-17": "s3cret", "bike-42": "pässwörd", "ped-1": "a:b=c$d"}
    for user, password in passwords.items():
        create = [] if path.exists() else ["-c"]
        subprocess.run([binary, *create, "-b", str(path), user, password], check=True)
    set_passwords(path, {"ours": "o"})  # ... and our writer keeps its lines
    lines = {line.split(":")[0]: line for line in path.read_text().splitlines()}
    assert sorted(lines) == sorted([*passwords, "ours"])
    for user, password in passwords.items():
        assert verify(lines[user], password)
        assert not verify(lines[user], password[:-1])


@pytest.mark.mosquitto
def test_mosquitto_accepts_our_password_file() -> None:
    need_mosquitto()
    passwords = {"car-17": "s3cret", "bike-42": "pässwörd"}
    broker = MosquittoBroker(allow_anonymous=False)
    path = broker.directory / "passwd"  # readable by the "mosquitto" user a root start drops to
    path.write_text("# accounts of this test\n")
    set_passwords(path, passwords, mode=0o644)
    broker.config_file.write_text(broker.config_file.read_text() + f"password_file {path}\n")

    def connect(user: str | None, password: str | None) -> None:
        settings = BrokerSettings(url=broker.url, username=user, password=password)
        transport = Transport(settings, client_id=f"c-{user}", sink=lambda e: None)
        transport.start(timeout=3)
        transport.stop()

    with broker:
        for user, password in passwords.items():
            connect(user, password)
        refused: list[tuple[str | None, str | None]] = [
            ("car-17", "s3cre"),
            ("bike-42", "passwörd"),
            ("nobody", "s3cret"),
            (None, None),
        ]
        for who, secret in refused:
            with pytest.raises(LdmError, match="no connection"):
                connect(who, secret)
