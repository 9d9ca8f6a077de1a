"""The keyed digest of an episode log: how ``brave6d evaluate`` tells a log the server wrote from
one changed afterwards (docs/SECURITY.md says what it proves and what it does not).

The server holds a secret key (32 random bytes; the key file holds them as 64 hex digits, mode
0600): ``--log-key FILE``, else ``$BRAVE6D_LOG_KEY`` (a path), else
``$XDG_CONFIG_HOME/brave6d/episode-log.key`` (``~/.config/...``), which a server makes on first
use. Every line of an episode's log is fed, byte for byte as written, into an HMAC-SHA256 under
the key; when the episode closes the server appends one last record, ``digest``: the algorithm,
the key's id (a hash of the key that does not reveal it), the number of lines covered and the
HMAC. The ``submit`` record holds the SHA-256 of the final depth image, so the digest covers that
file too.

:func:`check_log_digest` reads a log back: ``verified`` (the log, and its depth image, are the
bytes the server signed), ``unsigned`` (no digest: a log written before digests, or by a server
stopped before the episode closed) or ``unknown key`` (signed with a key this machine does not
hold); a log whose bytes differ from what was signed is a :class:`DataError` naming the file and
the episode. Only the holder of the key can make a digest that verifies, and only it can check one.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from brave6d.core.errors import DataError

#: Environment variable naming the key file (a path), read when no ``--log-key`` is given.
LOG_KEY_ENV = "BRAVE6D_LOG_KEY"
#: The key file's name in the configuration folder.
LOG_KEY_FILE = "episode-log.key"
#: Bytes of a key.
KEY_BYTES = 32
#: The algorithm the ``digest`` record names.
ALGORITHM = "hmac-sha256"
#: What the HMAC starts with (so that a digest of this format is never valid for another use of the key).
_DOMAIN = b"brave6d-episode-log/1\n"
_KEY_ID = b"brave6d-episode-log-key-id/1\n"

DigestStatus = Literal["verified", "unsigned", "unknown key"]


@dataclass(frozen=True)
class LogKey:
    """A secret key (never printed) and its public id (the first 16 hex digits of a hash of it)."""

    secret: bytes
    source: str = "given"

    def __post_init__(self) -> None:
        if len(self.secret) != KEY_BYTES:
            raise ValueError(f"a log key has {KEY_BYTES} bytes, got {len(self.secret)}")

    @property
    def key_id(self) -> str:
        return hashlib.sha256(_KEY_ID + self.secret).hexdigest()[:16]

    def mac(self) -> hmac.HMAC:
        """A fresh HMAC-SHA256 of a log under this key (the domain prefix already fed)."""
        return hmac.new(self.secret, _DOMAIN, hashlib.sha256)

    def __repr__(self) -> str:  # the secret stays out of logs and tracebacks
        return f"LogKey(key_id={self.key_id!r}, source={self.source!r})"

    @classmethod
    def random(cls) -> LogKey:
        return cls(secrets.token_bytes(KEY_BYTES), "random")


def default_log_key_path(environ: dict[str, str] | None = None) -> Path:
    """``$BRAVE6D_LOG_KEY``, else ``$XDG_CONFIG_HOME/brave6d/episode-log.key`` (``~/.config``)."""
    env = os.environ if environ is None else environ
    given = env.get(LOG_KEY_ENV, "").strip()
    if given:
        return Path(given).expanduser()
    config = env.get("XDG_CONFIG_HOME", "").strip()
    return (Path(config) if config else Path.home() / ".config") / "brave6d" / LOG_KEY_FILE


def read_log_key(path: Path | str) -> LogKey:
    """The key in ``path`` (64 hex digits); :class:`DataError` naming the file otherwise."""
    p = Path(path)
    try:
        text = p.read_text(encoding="ascii").strip()
    except FileNotFoundError:
        raise DataError(f"{p}: log key file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{p}: cannot read the log key ({exc})") from None
    try:
        secret = bytes.fromhex(text)
    except ValueError:
        secret = b""
    if len(secret) != KEY_BYTES:
        raise DataError(f"{p}: a log key file holds {2 * KEY_BYTES} hex digits (make one by deleting it: the "
                        "server writes a new one)")
    return LogKey(secret, str(p))


def server_log_key(path: Path | str | None = None) -> LogKey:
    """The key a server signs with: the one in ``path`` (default :func:`default_log_key_path`), made
    there (mode 0600, never overwritten) when the file does not exist."""
    p = Path(path) if path is not None else default_log_key_path()
    if not p.exists():
        p.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:  # another server made it meanwhile: use that one
            return read_log_key(p)
        with os.fdopen(fd, "w", encoding="ascii") as handle:
            handle.write(secrets.token_bytes(KEY_BYTES).hex() + "\n")
            handle.flush()
            os.fsync(handle.fileno())
    return read_log_key(p)


def evaluation_log_key(path: Path | str | None = None) -> LogKey | None:
    """The key ``evaluate`` checks digests with: ``path``'s (an error when it cannot be read), else the
    default key file's when it exists, else None (digests cannot be checked here)."""
    if path is not None:
        return read_log_key(path)
    p = default_log_key_path()
    return read_log_key(p) if p.is_file() else None


def digest_record_json(key: LogKey, mac: hmac.HMAC, lines: int) -> dict[str, object]:
    """The fields of the ``digest`` record that closes a log (see :mod:`brave6d.serve.episode_log`)."""
    return {"event": "digest", "algorithm": ALGORITHM, "key_id": key.key_id, "lines": lines,
            "digest": mac.hexdigest()}


@dataclass(frozen=True)
class DigestCheck:
    """What :func:`check_log_digest` found: the status and the id of the key that signed (None: unsigned)."""

    status: DigestStatus
    key_id: str | None = None


@dataclass(frozen=True)
class SignedDigest:
    """A log's ``digest`` record as :func:`check_log_digest` needs it."""

    key_id: str
    lines: int
    digest: str


def check_log_digest(path: Path | str, key: LogKey | None, episode_id: str, signed: SignedDigest | None,
                     depth_file: Path | None = None, depth_sha256: str | None = None) -> DigestCheck:
    """Check the log at ``path`` (episode ``episode_id``, whose last record is ``signed``: None when it
    has no ``digest`` record) with ``key`` and, when the log names one, its final depth image against
    ``depth_sha256`` (a depth image that is not there is left to the scoring that needs it).

    A depth image whose SHA-256 is not the logged one and a digest that does not match the lines
    before it are each a :class:`DataError` naming the file and the episode: the log (or its image)
    was changed after the server wrote it."""
    p = Path(path)
    if depth_file is not None and depth_sha256 is not None and depth_file.exists():  # absent: VSD says so
        try:
            actual = hashlib.sha256(depth_file.read_bytes()).hexdigest()
        except OSError as exc:
            raise DataError(f"{depth_file}: episode {episode_id}: cannot read the final depth image ({exc})") from None
        if actual != depth_sha256:
            raise DataError(f"{depth_file}: episode {episode_id}: the final depth image is not the one the server "
                            "logged (its SHA-256 differs): it was changed after the episode; refused")
    if signed is None:
        return DigestCheck("unsigned")
    head = p.read_bytes().rstrip(b"\n").rpartition(b"\n")[0]
    covered = head + b"\n" if head else b""
    lines = covered.count(b"\n")
    if lines != signed.lines:
        raise DataError(f"{p}: episode {episode_id}: the digest covers {signed.lines} lines but the log has {lines} "
                        "before it: lines were added or removed after the server closed it; refused")
    if key is None or key.key_id != signed.key_id:
        return DigestCheck("unknown key", signed.key_id)
    mac = key.mac()
    mac.update(covered)
    if not hmac.compare_digest(mac.hexdigest(), signed.digest):
        raise DataError(f"{p}: episode {episode_id}: the log does not match the digest the server wrote when it "
                        "closed the episode: it was changed afterwards (an estimate, a pose or a count); refused")
    return DigestCheck("verified", signed.key_id)
