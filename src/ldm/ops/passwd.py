"""Mosquitto password files, written without mosquitto_passwd.

Each line is one account, in Mosquitto 2's PBKDF2-SHA512 format (what ``mosquitto_passwd``
writes, with the same defaults)::

    USER:$7$ITERATIONS$base64(SALT)$base64(PBKDF2-HMAC-SHA512(PASSWORD, SALT, ITERATIONS, 64))

with ITERATIONS = 101, a random 12-byte SALT, standard base64 with padding and the password
as UTF-8. `verify` also accepts the older lines Mosquitto still reads::

    USER:$6$base64(SALT)$base64(SHA512(PASSWORD + SALT))

    set_passwords("passwd", {"car-17": "s3cret"})   # create or extend, atomically
    set_passwords("passwd", {"car-18": "pw"}, replace=False)   # never change an account
    verify(Path("passwd").read_text().splitlines()[0], "s3cret")
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import hashlib
import hmac
import os
import secrets
import tempfile
from collections.abc import Mapping
from pathlib import Path

from ldm.errors import PasswordFileError

__all__ = [
    "ITERATIONS",
    "SALT_BYTES",
    "check_user",
    "hash_password",
    "password_line",
    "random_password",
    "set_passwords",
    "verify",
]

ITERATIONS = 101
SALT_BYTES = 12
_KEY_BYTES = 64
_MAX_USER_BYTES = 65535  # an MQTT string


def check_user(user: str) -> str:
    """Return `user` if Mosquitto can store it in a password file, else raise.

    Refused: the empty name, ``:`` (the field separator), control characters such as a
    newline, leading or trailing blanks (Mosquitto trims them), a leading ``#`` (a comment)
    and names that are not UTF-8 or longer than an MQTT string.
    """
    problem = None
    if not user:
        problem = "it is empty"
    elif ":" in user:
        problem = "it contains ':'"
    elif any(ord(c) < 32 or ord(c) == 127 for c in user):
        problem = "it contains a control character (newline, tab, ...)"
    elif user != user.strip():
        problem = "it starts or ends with a blank"
    elif user.startswith("#"):
        problem = "it starts with '#' (a comment in a password file)"
    else:
        try:
            size = len(user.encode("utf-8"))
        except UnicodeEncodeError:
            problem = "it is not valid UTF-8"
        else:
            if size > _MAX_USER_BYTES:
                problem = f"it is longer than {_MAX_USER_BYTES} bytes"
    if problem is not None:
        raise PasswordFileError(f"bad user name {user!r}: {problem}")
    return user


def _password_bytes(password: str) -> bytes:
    if not password:
        raise PasswordFileError("empty password")
    # surrogateescape: bytes from a non-UTF-8 command line are hashed as given.
    return password.encode("utf-8", "surrogateescape")


def hash_password(password: str, *, salt: bytes | None = None, iterations: int = ITERATIONS) -> str:
    """The ``$7$ITERATIONS$SALT$HASH`` field of a password file line (random salt by default)."""
    if iterations < 1:
        raise PasswordFileError(f"iterations must be at least 1, not {iterations}")
    salt = secrets.token_bytes(SALT_BYTES) if salt is None else salt
    key = hashlib.pbkdf2_hmac("sha512", _password_bytes(password), salt, iterations, _KEY_BYTES)
    return f"$7${iterations}${_b64(salt)}${_b64(key)}"


def password_line(user: str, password: str) -> str:
    """One password file line, ``USER:$7$...``, without the newline."""
    return f"{check_user(user)}:{hash_password(password)}"


def random_password() -> str:
    """24 URL-safe random characters (18 bytes from `secrets`)."""
    return secrets.token_urlsafe(18)


def verify(line: str, password: str) -> bool:
    """True if `password` matches the line's hash (``$7$`` or ``$6$``).

    A line that is not ``USER:HASH`` in one of those formats raises `PasswordFileError`.
    """
    user, sep, field = line.rstrip("\r\n").partition(":")
    if not sep:
        raise PasswordFileError("malformed password line: no ':' after the user name")
    parts = field.strip().split("$")
    secret = password.encode("utf-8", "surrogateescape")
    try:
        if len(parts) == 5 and parts[:2] == ["", "7"]:
            iterations = int(parts[2])
            if iterations < 1:
                raise ValueError(iterations)
            salt, expected = _unb64(parts[3]), _unb64(parts[4])
            key = hashlib.pbkdf2_hmac("sha512", secret, salt, iterations, len(expected))
        elif len(parts) == 4 and parts[:2] == ["", "6"]:
            salt, expected = _unb64(parts[2]), _unb64(parts[3])
            key = hashlib.sha512(secret + salt).digest()
        else:
            raise ValueError(parts[:2])
    except (ValueError, binascii.Error):
        raise PasswordFileError(
            f"malformed password line for user {user.strip()!r}: "
            "expected $7$ITERATIONS$SALT$HASH or $6$SALT$HASH"
        ) from None
    return bool(expected) and hmac.compare_digest(key, expected)


def set_passwords(
    path: str | os.PathLike[str],
    passwords: Mapping[str, str],
    *,
    mode: int = 0o640,
    replace: bool = True,
) -> list[str]:
    """Create or extend a password file: one line per user in `passwords`.

    With `replace`, a user's existing line is replaced in place (further lines of the same
    user are dropped); without it, a user already in the file keeps its password and is
    returned among the users kept. Every other line is kept as it was. The new file is
    written next to the old one and renamed over it, so readers see the old or the new
    file, never a part; it gets `mode` and, where permitted, the old file's owner.
    Returns the users of `passwords` whose existing lines were kept (none with `replace`).
    """
    for user in passwords:
        check_user(user)
    target = Path(os.path.realpath(path))
    try:
        old = target.read_text(encoding="utf-8", errors="surrogateescape").splitlines()
        status = target.stat()
        owner: tuple[int, int] | None = (status.st_uid, status.st_gid)
    except FileNotFoundError:
        old, owner = [], None
    present = {line.split(":", 1)[0].strip() for line in old if ":" in line}
    kept = [] if replace else [user for user in passwords if user in present]
    lines = {user: password_line(user, pw) for user, pw in passwords.items() if user not in kept}
    out: list[str] = []
    done: set[str] = set()
    for existing in old:
        name = existing.split(":", 1)[0].strip() if ":" in existing else None
        if name is not None and name in lines:
            if name not in done:
                out.append(lines[name])
                done.add(name)
        else:
            out.append(existing)
    out += [line for user, line in lines.items() if user not in done]
    text = "".join(line + "\n" for line in out)

    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", errors="surrogateescape") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        if owner is not None:
            # Keeps the old owner where allowed (root may); otherwise the writer owns the file.
            with contextlib.suppress(PermissionError):
                os.chown(tmp, *owner)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return kept


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _unb64(text: str) -> bytes:
    return base64.b64decode(text.strip(), validate=True)
