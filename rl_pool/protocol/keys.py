"""The pool's secret key: only its holders can steer a pool.

Threat model. Anyone who can *write* the pool directory can delete or replace
files there: that is a denial of service no file format prevents. What must
not follow from write access is *steering*: planting an agent that gets
selected, forging a selection, or changing the pool's settings. So every file
that decides something carries an HMAC-SHA256 (RFC 2104) over its canonical
JSON: ``pool.json``, each deposit's metrics (which hold the agent's SHA-256,
so the agent file is covered too), each ``selected.json``, ``best.json``.
A file without a valid signature never decides anything; readers skip it
and say why.

The key is 32 random bytes, created with the pool and kept *outside* it by
default (``~/.config/rl-pool/keys/<pool id>.key``, mode 0600), so read access
to the pool does not reveal it and write access to the pool cannot replace
it. On a cluster whose members do not share that home directory, give the
same key file to every member (``--key-file``, or ``RL_POOL_KEY_FILE``), or
the key itself in hex in ``RL_POOL_KEY``. ``pool.json`` records a fingerprint
of the key (an HMAC of a fixed string: it reveals nothing about the key) so a
member given the wrong key stops with one clear line instead of rejecting
every file it reads.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import stat

from rl_pool.errors import UsageError

KEY_BYTES = 32
SIGNATURE = "signature"
_FINGERPRINT_MSG = b"rl-pool key fingerprint v1"


def canonical(doc: dict) -> bytes:
    """The bytes a signature covers: the document without its signature, keys sorted, no spaces."""
    body = {k: v for k, v in doc.items() if k != SIGNATURE}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


class Key:
    """A pool key; ``sign`` and ``verify`` work on JSON-able dicts."""

    def __init__(self, secret: bytes):
        if len(secret) < 16:
            raise ValueError("a pool key needs at least 16 bytes")
        self._secret = bytes(secret)

    def __repr__(self) -> str:  # never print the secret
        return f"Key(fingerprint={self.fingerprint()})"

    def fingerprint(self) -> str:
        return hmac.new(self._secret, _FINGERPRINT_MSG, hashlib.sha256).hexdigest()[:32]

    def mac(self, doc: dict) -> str:
        return hmac.new(self._secret, canonical(doc), hashlib.sha256).hexdigest()

    def sign(self, doc: dict) -> dict:
        """``doc`` with its signature added (any old one replaced)."""
        body = {k: v for k, v in doc.items() if k != SIGNATURE}
        return body | {SIGNATURE: self.mac(body)}

    def verify(self, doc) -> bool:
        sig = doc.get(SIGNATURE) if isinstance(doc, dict) else None
        if not isinstance(sig, str):
            return False
        try:
            return hmac.compare_digest(sig, self.mac(doc))
        except (TypeError, ValueError):  # not canonical JSON (NaN, odd types): not signed by us
            return False

    def why_invalid(self, doc) -> str | None:
        """None if ``doc`` carries a valid signature, else the reason in a few words."""
        if not isinstance(doc, dict):
            return "not a JSON object"
        if SIGNATURE not in doc:
            return "unsigned"
        return None if self.verify(doc) else "bad signature"


# ---------------------------------------------------------------- where keys live
def new_pool_id() -> str:
    return secrets.token_hex(8)


def default_path(pool_id: str) -> str:
    base = os.environ.get("XDG_CONFIG_HOME") or os.path.join(os.path.expanduser("~"), ".config")
    return os.path.join(base, "rl-pool", "keys", f"{pool_id}.key")


def _write_new(path: str, secret: bytes) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), mode=0o700, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        os.write(fd, secret.hex().encode() + b"\n")
        os.fsync(fd)
    finally:
        os.close(fd)


def _read(path: str) -> Key:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise UsageError(f"no pool key at {path} (give the pool's key with --key-file or RL_POOL_KEY_FILE)") \
            from None
    except OSError as exc:
        raise UsageError(f"cannot read the pool key {path}: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size > 1024:
            raise UsageError(f"{path} is not a pool key file")
        text = os.read(fd, 1025).decode("ascii", "replace").strip()
    finally:
        os.close(fd)
    if st.st_mode & 0o077:
        raise UsageError(f"pool key {path} is readable by others (mode {st.st_mode & 0o777:o}); "
                         f"chmod 600 {path}")
    try:
        return Key(bytes.fromhex(text))
    except ValueError:
        raise UsageError(f"{path} does not hold a pool key (hex)") from None


def from_environment() -> tuple[Key | None, str | None]:
    """``(key, source)`` from ``RL_POOL_KEY`` (hex) or ``RL_POOL_KEY_FILE``, else ``(None, None)``."""
    hexkey = os.environ.get("RL_POOL_KEY")
    if hexkey:
        try:
            return Key(bytes.fromhex(hexkey.strip())), "RL_POOL_KEY"
        except ValueError:
            raise UsageError("RL_POOL_KEY must be the key in hex (at least 32 hex digits)") from None
    path = os.environ.get("RL_POOL_KEY_FILE")
    if path:
        return _read(path), path
    return None, None


def create(pool_id: str, key_file: str | None = None) -> tuple[Key, str]:
    """The key of a pool being created: the given or environment key, else a new one stored
    (mode 0600) at ``key_file`` or the default path. Returns ``(key, where)``."""
    if key_file:
        if os.path.lexists(key_file):
            return _read(key_file), key_file
        key = Key(secrets.token_bytes(KEY_BYTES))
        _write_new(key_file, key._secret)
        return key, key_file
    env_key, source = from_environment()
    if env_key is not None:
        return env_key, source
    path = default_path(pool_id)
    key = Key(secrets.token_bytes(KEY_BYTES))
    _write_new(path, key._secret)
    return key, path


def load(pool_id: str, fingerprint: str, key_file: str | None = None) -> Key:
    """The key of an existing pool (``key_file``, the environment, or the default path),
    checked against the fingerprint ``pool.json`` records."""
    if key_file:
        key, where = _read(key_file), key_file
    else:
        key, where = from_environment()
        if key is None:
            where = default_path(pool_id)
            key = _read(where)
    if not hmac.compare_digest(key.fingerprint(), str(fingerprint)):
        raise UsageError(f"the key from {where} is not this pool's key (fingerprints differ)")
    return key
