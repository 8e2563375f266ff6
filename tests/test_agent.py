"""Agent files: round trip, the public API, and refusal of anything not an agent."""

import io
import json
import os
import zipfile

import numpy as np
import pytest
import scipy.stats

from rl_pool import Agent
from rl_pool.errors import AgentFileError, EnvError
from rl_pool.learning import envs
from rl_pool.maths import policy
from rl_pool.maths.agent import AgentMeta, max_file_bytes

from .helpers import META, Evil, agent


def test_round_trip_is_exact(tmp_path):
    a = agent(1)
    a = a.evolve(opt_m={"w": a.params["w"] * 2}, opt_v={"w": a.params["w"] ** 2}, opt_t=7.0)
    path = tmp_path / "a.npz"
    a.save(path)
    b = Agent.load(path)
    assert b.meta == a.meta
    for x, y in [(a.params["w"], b.params["w"]), (a.norm.mean, b.norm.mean), (a.norm.m2, b.norm.m2),
                 (a.opt_m["w"], b.opt_m["w"]), (a.opt_v["w"], b.opt_v["w"])]:
        np.testing.assert_array_equal(x, y)
    assert (b.norm.count, b.opt_t) == (a.norm.count, a.opt_t)
    assert a.to_bytes() == b.to_bytes()


def test_api_shapes_and_bounds():
    a = agent(2)
    obs = np.linspace(-1, 1, 8)
    alpha, beta = a.beta_params(obs)
    assert alpha.shape == beta.shape == (2,) and alpha.min() >= 1
    act = a.act(obs)
    np.testing.assert_allclose(act, -1 + 2 * alpha / (alpha + beta))
    rng = np.random.default_rng(0)
    samples = np.array([a.act(obs, rng=rng, deterministic=False) for _ in range(200)])
    assert samples.min() >= -1 and samples.max() <= 1


def test_log_prob_in_env_units_includes_the_jacobian():
    a = agent(3).evolve(meta=META.__class__(**{**META.__dict__, "action_low": (-2.0, 0.0),
                                                 "action_high": (2.0, 0.5)}))
    obs = np.arange(8.0) / 10
    action = np.array([0.7, 0.1])
    alpha, beta = a.beta_params(obs)
    u = (action - a.low) / (a.high - a.low)
    want = sum(scipy.stats.beta.logpdf(u[j], alpha[j], beta[j]) - np.log(a.high[j] - a.low[j]) for j in range(2))
    assert a.log_prob(obs, action) == pytest.approx(want, rel=1e-10)


def test_log_prob_at_action_bounds_is_finite():
    a = agent(4)
    assert np.isfinite(a.log_prob(np.zeros(8), np.array([-1.0, 1.0])))


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _arrays(a):
    with np.load(io.BytesIO(a.to_bytes()), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def test_pickled_object_is_refused_and_never_run(tmp_path):
    marker = tmp_path / "ran"
    arrays = _arrays(agent()) | {"param.w": np.array([Evil(marker)], dtype=object)}
    with pytest.raises(AgentFileError, match="unreadable"):
        Agent.from_bytes(_npz(**arrays))
    assert not marker.exists()


@pytest.mark.parametrize("what", ["text", "pickle", "npy", "empty"])
def test_files_that_are_not_zip_archives_are_refused_as_such(tmp_path, what):
    """A text file, a bare pickle or .npy is "not an rl-pool agent file"; the reply never passes on
    numpy's advice to load a pickle unsafely, and the pickle never runs."""
    import pickle

    marker = tmp_path / "ran"
    data = {"text": b"root:x:0:0:root:/root:/bin/bash\n", "pickle": pickle.dumps(Evil(marker)),
            "npy": _npy(np.zeros(3)), "empty": b""}[what]
    with pytest.raises(AgentFileError, match="not an rl-pool agent file") as err:
        Agent.from_bytes(data, source="x.npz")
    assert "pickle" not in str(err.value) and not marker.exists()


def _npy(arr):
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


@pytest.mark.parametrize("change, match", [
    ({"param.w": np.zeros((3, 3))}, "shape"),
    ({"adam_v.w": -np.ones((9, 4))}, "negative"),
    ({"obs_mean": np.full(8, np.nan)}, "non-finite"),
    ({"meta": np.array("{not json")}, "JSON"),
    ({"meta": np.array(json.dumps({"format": "something-else"}))}, "not an rl-pool agent"),
])
def test_inconsistent_files_are_refused(change, match):
    with pytest.raises(AgentFileError, match=match):
        Agent.from_bytes(_npz(**(_arrays(agent()) | change)))


def test_arrays_written_otherwise_load_to_the_same_agent():
    # to_bytes writes little-endian C-ordered float64 arrays, read straight from the bytes; big-endian,
    # Fortran-ordered and float32 arrays go through numpy's own reader
    a = agent(3)
    a = a.evolve(opt_m={"w": a.params["w"] * 2}, opt_v={"w": a.params["w"] ** 2}, opt_t=7.0)
    arrays = _arrays(a)

    def written(convert):
        return Agent.from_bytes(_npz(**{k: v if k == "meta" else convert(v) for k, v in arrays.items()}))

    for b in (written(lambda v: v.astype(">f8")), written(lambda v: np.asfortranarray(v) if v.ndim else v)):
        for x, y in [(a.params["w"], b.params["w"]), (a.opt_m["w"], b.opt_m["w"]), (a.opt_v["w"], b.opt_v["w"]),
                     (a.norm.mean, b.norm.mean), (a.norm.m2, b.norm.m2)]:
            np.testing.assert_array_equal(x, y)
        assert (b.meta, b.norm.count, b.opt_t) == (a.meta, a.norm.count, a.opt_t)
    single = written(lambda v: v.astype("<f4"))
    np.testing.assert_array_equal(single.params["w"], a.params["w"].astype(np.float32).astype(np.float64))


def test_a_float64_header_over_other_lengths_of_data_goes_to_numpys_reader():
    # the bytes are used directly only when their length is exactly the header's shape; else numpy
    # reads them as it always did: too few are refused, bytes past the array are ignored
    a = agent()
    arrays = _arrays(a)

    def with_param(raw):
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as zf:
            for k, v in arrays.items():
                zf.writestr(k + ".npy", raw if k == "param.w" else _npy(v))
        return Agent.from_bytes(buf.getvalue())

    data = _npy(arrays["param.w"])
    with pytest.raises(AgentFileError, match="unreadable"):
        with_param(data[:-8])
    np.testing.assert_array_equal(with_param(data + b"\0" * 8).params["w"], a.params["w"])


def test_garbage_and_missing_files(tmp_path):
    with pytest.raises(AgentFileError, match="unreadable"):
        Agent.from_bytes(b"PK\x03\x04 definitely not a zip")
    with pytest.raises(AgentFileError, match="missing"):
        Agent.from_bytes(_npz(x=np.zeros(3)))
    with pytest.raises(AgentFileError, match="cannot read"):
        Agent.load(tmp_path / "nope.npz")


def test_unbounded_or_discrete_action_spaces_are_refused():
    import gymnasium as gym

    class Unbounded(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (3,))
        action_space = gym.spaces.Box(-np.inf, np.inf, (2,))

    with pytest.raises(EnvError, match="unbounded"):
        envs.check("Unbounded-v0", Unbounded())
    with pytest.raises(EnvError, match="Discrete"):
        envs.make("CartPole-v1")
    with pytest.raises(EnvError, match="unknown"):
        envs.make("NoSuchEnv-v9")


def test_hostile_sizes_are_refused_before_allocation():
    import zipfile

    # An entry that really is big (9 M zeros compress to a few kB) is refused from the zip directory.
    huge = io.BytesIO()
    np.savez_compressed(huge, **(_arrays(agent()) | {"param.w": np.zeros((3000, 3000))}))
    assert len(huge.getvalue()) < 100_000
    with pytest.raises(AgentFileError, match="larger than its shape"):
        Agent.from_bytes(huge.getvalue())
    # A header that claims 2.5e9 elements over a tiny payload is refused without allocating them.
    with zipfile.ZipFile(io.BytesIO(agent().to_bytes())) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    header = np.lib.format.header_data_from_array_1_0(np.zeros((9, 4)))
    header["shape"] = (50_000, 50_000)
    out = io.BytesIO()
    np.lib.format.write_array_header_1_0(out, header)
    members["param.w.npy"] = out.getvalue() + b"\0" * 64
    fake = io.BytesIO()
    with zipfile.ZipFile(fake, "w") as zf:
        for n, b in members.items():
            zf.writestr(n, b)
    with pytest.raises(AgentFileError, match="unreadable"):
        Agent.from_bytes(fake.getvalue())


def test_a_meta_that_claims_huge_shapes_over_small_arrays_allocates_nothing_of_that_size():
    import tracemalloc

    arrays = _arrays(agent())
    meta = json.loads(str(arrays["meta"]))
    act = 1000  # with 100 000 observations: a (100 001, 2000) float64 matrix claimed, 1.6 GB
    meta |= {"obs_dim": 100_000, "act_dim": act, "action_low": [-1.0] * act, "action_high": [1.0] * act}
    data = _npz(**(arrays | {"meta": np.array(json.dumps(meta))}))
    tracemalloc.start()
    try:
        with pytest.raises(AgentFileError, match="shape"):
            Agent.from_bytes(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20_000_000


def test_a_compressed_member_that_inflates_past_its_stated_size_is_read_in_bounded_memory():
    import struct
    import tracemalloc
    import zlib

    # param.w's .npy, then 50 MiB of zeros, deflated to some 50 kB; the zip directory states the
    # size and CRC of the .npy alone, so a reader that inflates the whole member before cutting it
    # to the stated size holds 50 MiB for a file of 50 kB
    a = agent()
    arrays = _arrays(a)
    npy = _npy(arrays["param.w"])
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for k, v in arrays.items():
            if k == "param.w":
                zf.writestr(k + ".npy", npy + b"\0" * (50 << 20), compress_type=zipfile.ZIP_DEFLATED)
            else:
                zf.writestr(k + ".npy", _npy(v))
    data = bytearray(buf.getvalue())
    assert len(data) < 200_000
    at = data.index(b"PK\x01\x02")
    while True:  # the central directory entry of param.w.npy: its CRC and uncompressed size
        name_len = struct.unpack_from("<H", data, at + 28)[0]
        if bytes(data[at + 46:at + 46 + name_len]) == b"param.w.npy":
            struct.pack_into("<I", data, at + 16, zlib.crc32(npy))
            struct.pack_into("<I", data, at + 24, len(npy))
            break
        at = data.index(b"PK\x01\x02", at + 4)
    tracemalloc.start()
    try:
        b = Agent.from_bytes(bytes(data))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(b.params["w"], a.params["w"])  # numpy's reader reads what it needs
    assert peak < 20_000_000


def test_what_to_bytes_writes_takes_the_direct_path():
    # if numpy ever writes another header, agents still load (through numpy's reader), only slower:
    # this says so
    from rl_pool.maths.agent import _float64_header, array_shapes

    a = agent()
    with zipfile.ZipFile(io.BytesIO(a.to_bytes())) as zf:
        for key, shape in array_shapes(a.meta).items():
            info = zf.getinfo(key + ".npy")
            assert info.compress_type == zipfile.ZIP_STORED
            assert zf.read(info).startswith(_float64_header(shape)), key


def test_a_member_that_is_not_npy_is_refused_in_one_line():
    arrays = _arrays(agent())
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for k, v in arrays.items():
            zf.writestr(k + ".npy", b"not an npy at all" if k == "param.w" else _npy(v))
    with pytest.raises(AgentFileError, match=r"param\.w\.npy is not a \.npy array"):
        Agent.from_bytes(buf.getvalue())


OLD_FORMAT = os.path.join(os.path.dirname(__file__), "..", "results", "swimmer-v5", "best.npz")


def _reference_action(raw: dict, obs: np.ndarray) -> np.ndarray:
    """Format 1's linear-exp policy written out by hand from the file's raw arrays."""
    meta = json.loads(str(raw["meta"]))
    std = np.sqrt(raw["obs_m2"] / raw["obs_count"] + 1e-8)
    x = np.clip((obs - raw["obs_mean"]) / std, -10, 10)
    z = np.append(x, 1.0) @ raw["w"]
    ab = np.exp(np.minimum(z, 10.0)) + 1
    a, b = ab[: len(ab) // 2], ab[len(ab) // 2:]
    low, high = np.array(meta["action_low"]), np.array(meta["action_high"])
    return low + a / (a + b) * (high - low)


def test_format_1_files_load_and_act_identically(tmp_path):
    with np.load(OLD_FORMAT, allow_pickle=False) as z:
        raw = {k: z[k] for k in z.files}
    assert json.loads(str(raw["meta"]))["version"] == 1 and "w" in raw
    old = Agent.load(OLD_FORMAT)
    assert old.spec == policy.PolicySpec("linear", (), "exp")
    rng = np.random.default_rng(0)
    observations = rng.normal(scale=2.0, size=(50, old.meta.obs_dim))
    for obs in observations:
        np.testing.assert_allclose(old.act(obs), _reference_action(raw, obs), rtol=1e-12, atol=1e-14)
    # written again it is a format-2 file that acts the same, bit for bit
    old.save(tmp_path / "v2.npz")
    new = Agent.load(tmp_path / "v2.npz")
    assert new.meta == old.meta and json.loads(str(_arrays(new)["meta"]))["version"] == 2
    for obs in observations:
        np.testing.assert_array_equal(new.act(obs), old.act(obs))


def test_mlp_agent_round_trip_and_size_cap(tmp_path):
    meta = AgentMeta("HalfCheetah-v5", {}, 1000, 17, 6, (-1.0,) * 6, (1.0,) * 6,
                     policy.PolicySpec("mlp", (64, 64), "exp"))
    a = Agent.initial(meta, seed=5)
    assert set(a.params) == {"w0", "b0", "w1", "b1", "w2", "b2"}
    a.save(tmp_path / "m.npz")
    b = Agent.load(tmp_path / "m.npz")
    assert b.meta == meta and a.to_bytes() == b.to_bytes()
    obs = np.linspace(-1, 1, 17)
    np.testing.assert_array_equal(a.act(obs), b.act(obs))
    assert len(a.to_bytes()) <= max_file_bytes(meta)
    # the cap follows the pool's shapes: a linear Swimmer agent's is far below this MLP's
    assert len(agent().to_bytes()) <= max_file_bytes(META) < 150_000 < max_file_bytes(meta)
