"""The shared pool directory: file names and paths (:mod:`.layout`), create-once decisions
(:mod:`.claim`), keys and signatures (:mod:`.keys`), deposits (:mod:`.deposits`), the selection
rule (:mod:`.selection`, pure), opening a pool and deciding its selections (:mod:`.pool`),
heartbeats, the barrier, and the filesystem checks (:mod:`.doctor`, :mod:`.peer_race`).
Described as a whole in ``docs/protocol.md``. Knows nothing of environments or training."""
