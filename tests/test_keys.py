"""The pool key: HMAC signatures (against Python's hmac as the reference), key files, fingerprints."""

import hashlib
import hmac
import json
import os
import stat

import pytest

from rl_pool.errors import UsageError
from rl_pool.protocol import deposits, keys, layout


@pytest.fixture
def home(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    monkeypatch.delenv("RL_POOL_KEY", raising=False)
    monkeypatch.delenv("RL_POOL_KEY_FILE", raising=False)
    return tmp_path


def test_signature_is_hmac_sha256_of_the_canonical_json():
    key = keys.Key(b"k" * 32)
    doc = {"iteration": 3, "member": 1, "eval_return": 12.5, "agent_sha256": "ab" * 32}
    signed = key.sign(doc)
    body = json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()
    assert signed["signature"] == hmac.new(b"k" * 32, body, hashlib.sha256).hexdigest()
    assert key.verify(signed) and key.why_invalid(signed) is None
    # the signature survives a JSON round trip with another key order and indentation
    again = json.loads(json.dumps(dict(reversed(list(signed.items()))), indent=3))
    assert key.verify(again)


@pytest.mark.parametrize("change", [{"eval_return": 12.6}, {"agent_sha256": "cd" * 32}, {"member": 2},
                                   {"extra": 1}])
def test_any_change_breaks_the_signature(change):
    key = keys.Key(b"k" * 32)
    signed = key.sign({"iteration": 3, "member": 1, "eval_return": 12.5, "agent_sha256": "ab" * 32})
    assert key.why_invalid(signed | change) == "bad signature"


def test_unsigned_wrong_key_and_odd_documents_are_refused():
    key, other = keys.Key(b"k" * 32), keys.Key(b"x" * 32)
    doc = {"iteration": 1}
    assert key.why_invalid(doc) == "unsigned"
    assert key.why_invalid(other.sign(doc)) == "bad signature"
    assert key.why_invalid([1, 2]) == "not a JSON object"
    assert not key.verify({"signature": 5}) and not key.verify({"a": float("nan"), "signature": "00"})
    assert "k" * 8 not in repr(key)


def test_new_key_lives_outside_the_pool_with_mode_600(home):
    key, where = keys.create("abc123")
    assert where == str(home / "config/rl-pool/keys/abc123.key")
    assert stat.S_IMODE(os.stat(where).st_mode) == 0o600
    again = keys.load("abc123", key.fingerprint())
    assert again.fingerprint() == key.fingerprint()
    with pytest.raises(UsageError, match="not this pool's key"):
        keys.load("abc123", "0" * 32)
    with pytest.raises(UsageError, match="no pool key"):
        keys.load("other", key.fingerprint())


def test_key_file_and_environment(home, monkeypatch):
    path = str(home / "shared.key")
    key, where = keys.create("id1", key_file=path)
    assert where == path and keys.create("id2", key_file=path)[0].fingerprint() == key.fingerprint()
    os.chmod(path, 0o644)
    with pytest.raises(UsageError, match="readable by others"):
        keys.load("id1", key.fingerprint(), key_file=path)
    os.chmod(path, 0o600)
    monkeypatch.setenv("RL_POOL_KEY_FILE", path)
    assert keys.load("id1", key.fingerprint()).fingerprint() == key.fingerprint()
    monkeypatch.delenv("RL_POOL_KEY_FILE")
    monkeypatch.setenv("RL_POOL_KEY", open(path).read().strip())
    assert keys.load("whatever", key.fingerprint()).fingerprint() == key.fingerprint()
    monkeypatch.setenv("RL_POOL_KEY", "not hex")
    with pytest.raises(UsageError, match="hex"):
        keys.load("whatever", key.fingerprint())


def test_a_special_file_is_not_read_as_a_key(home):
    fifo = home / "fifo.key"
    os.mkfifo(fifo)
    with pytest.raises(UsageError, match="not a pool key file"):
        keys.load("x", "0", key_file=str(fifo))  # returns at once: opened non-blocking
    os.symlink("/dev/zero", home / "zero.key")
    with pytest.raises(UsageError, match="cannot read"):
        keys.load("x", "0", key_file=str(home / "zero.key"))  # symlinks are not followed


@pytest.mark.multiprocess
def test_forged_deposits_and_selections_are_never_adopted_in_a_live_pool(tmp_path):
    """An attacker with write access but no key plants a winning deposit and selections created
    before the honest members decide: none is adopted, and the pool completes."""
    import time

    import numpy as np

    from rl_pool.protocol import pool

    from .conftest import SHORT, spawn
    from .helpers import agent

    d = tmp_path / "pool"
    procs = [spawn("train", "--pool-dir", d, "--pool-size", 3, "--member", m, "--iterations", 4, *SHORT,
                   "--quorum", 2, "--heartbeat-timeout", 1, "--quiet") for m in (0, 1)]
    deadline = time.time() + 60
    while not (d / "iterations/000000/selected.json").exists() and time.time() < deadline:
        time.sleep(0.01)
    evil = agent(7)
    data = evil.to_bytes()
    sha = hashlib.sha256(data).hexdigest()
    for i in range(1, 5):
        it = d / f"iterations/{i:06d}"
        it.mkdir(parents=True, exist_ok=True)
        (it / "member-002.npz").write_bytes(data)
        (it / "member-002.json").write_text(json.dumps(
            {"iteration": i, "member": 2, "eval_return": 1e12, "eval_score": 1e12, "agent_sha256": sha,
             "signature": "0" * 64}))
        if i >= 2:  # a selection of the future, in place before anyone decides
            (it / "selected.json").write_text(json.dumps(
                {"iteration": i, "member": 2, "winner": "branch", "eval_return": 1e12, "score": 1e12,
                 "agent": f"iterations/{i:06d}/member-002.npz", "agent_sha256": sha, "considered": [],
                 "skipped": []}))
    for p in procs:
        _, err = p.communicate(timeout=240)
        assert p.returncode == 0, err
    paths = layout.Paths(d)
    assert pool.attach_key(paths)
    for i in range(1, 5):
        sel = json.loads((d / f"iterations/{i:06d}/selected.json").read_text())
        assert paths.key.verify(sel) and sel["agent_sha256"] != sha and sel["member"] != 2
        (skip,) = sel["skipped"]
        assert skip["member"] == 2 and "not written by a key holder" in skip["reason"]
    assert not np.array_equal(deposits.load_selected_agent(paths, 4).params["w"], evil.params["w"])
    assert json.loads((d / "best.json").read_text())["agent_sha256"] != sha
