"""Shard assignment (services/common/sharding.py): the same in every process, every stream owned by exactly one of
N = 1..5 replicas, balanced, few streams moving when a replica is added, and settings that refuse what cannot work."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter

import pytest
from pydantic import ValidationError

from services.common.errors import ConfigError
from services.common.sharding import ShardSettings, ordinal_from_pod_name, owns, shard_of
from tests.conftest import REPO

STREAMS = [f"cam{i}" for i in range(1000)]
COUNTS = range(1, 6)

_ASSIGN = """
import json, sys
from services.common.sharding import shard_of
streams = json.load(sys.stdin)
print(json.dumps({n: [shard_of(s, n) for s in streams] for n in range(1, 6)}))
"""


def _assignments() -> dict[str, list[int]]:
    return {str(n): [shard_of(s, n) for s in STREAMS] for n in COUNTS}


@pytest.mark.parametrize("hash_seed", ["0", "12345"])
def test_other_processes_assign_the_same_shards(hash_seed):
    """Each replica computes ownership in its own process: a salted hash (Python's hash()) would split differently."""
    env = {**os.environ, "PYTHONHASHSEED": hash_seed}
    out = subprocess.run([sys.executable, "-c", _ASSIGN], input=json.dumps(STREAMS), capture_output=True,
                         text=True, cwd=REPO, env=env, timeout=30, check=True).stdout
    assert json.loads(out) == _assignments()


def test_known_assignments_are_pinned():
    """Changing the hash would move every stream away from its durable map: this fails first."""
    assert [shard_of("cam0", n) for n in COUNTS] == [0, 0, 2, 2, 4]
    assert [shard_of("dock_3", n) for n in COUNTS] == [0, 1, 1, 3, 3]
    assert [shard_of("lobby-east", n) for n in COUNTS] == [0, 0, 0, 0, 4]


@pytest.mark.parametrize("count", COUNTS)
def test_every_stream_is_owned_by_exactly_one_shard(count):
    for stream in STREAMS:
        owners = [shard for shard in range(count) if owns(stream, shard, count)]
        assert owners == [shard_of(stream, count)], stream


@pytest.mark.parametrize("count", COUNTS)
def test_shards_are_roughly_balanced(count):
    sizes = Counter(shard_of(s, count) for s in STREAMS)
    assert set(sizes) == set(range(count))
    expected = len(STREAMS) / count
    assert all(abs(n - expected) < 0.2 * expected for n in sizes.values()), sizes


@pytest.mark.parametrize("count", range(1, 5))
def test_adding_a_replica_moves_only_the_streams_it_takes(count):
    """N → N+1: a stream either stays or moves to the new shard, about 1/(N+1) of them; none change old owners."""
    before = [shard_of(s, count) for s in STREAMS]
    after = [shard_of(s, count + 1) for s in STREAMS]
    moved = [(b, a) for b, a in zip(before, after) if a != b]
    assert all(a == count for _, a in moved)
    assert 0.5 / (count + 1) < len(moved) / len(STREAMS) < 1.5 / (count + 1)


@pytest.mark.parametrize(("name", "ordinal"), [("mapstore-0", 0), ("mapstore-2", 2), ("kmvipe-ba-13", 13)])
def test_pod_name_ordinal(name, ordinal):
    assert ordinal_from_pod_name(name) == ordinal


@pytest.mark.parametrize("name", ["", "mapstore", "mapstore-", "mapstore-02", "mapstore--1", "Mapstore-1"])
def test_pod_names_without_an_ordinal_are_refused(name):
    with pytest.raises(ValueError, match="KMVIPE_SHARD_INDEX"):
        ordinal_from_pod_name(name)


@pytest.fixture
def env(monkeypatch):
    for var in ("KMVIPE_SHARD_INDEX", "KMVIPE_SHARD_COUNT", "KMVIPE_SHARD_POD_NAME", "HOSTNAME"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.chdir(REPO / "tests")  # no .env file there
    return monkeypatch


def test_defaults_own_every_stream(env):
    env.setenv("HOSTNAME", "workstation-7")  # a host name that merely looks like a pod's is not a shard
    cfg = ShardSettings()
    assert (cfg.index, cfg.count) == (0, 1)
    assert all(cfg.owns(s) for s in STREAMS[:50])


def test_index_from_the_pod_name(env):
    env.setenv("KMVIPE_SHARD_COUNT", "3")
    env.setenv("HOSTNAME", "mapstore-1")
    assert ShardSettings().index == 1
    env.setenv("KMVIPE_SHARD_POD_NAME", "mapstore-2")  # the downward API wins over $HOSTNAME
    cfg = ShardSettings()
    assert cfg.index == 2
    assert [cfg.owns(s) for s in STREAMS[:50]] == [shard_of(s, 3) == 2 for s in STREAMS[:50]]
    env.setenv("KMVIPE_SHARD_INDEX", "0")  # an explicit index wins over both
    assert ShardSettings().index == 0


@pytest.mark.parametrize(("settings", "message"), [
    ({"KMVIPE_SHARD_COUNT": "0"}, "greater than or equal to 1"),
    ({"KMVIPE_SHARD_COUNT": "2", "KMVIPE_SHARD_INDEX": "-1"}, "greater than or equal to 0"),
    ({"KMVIPE_SHARD_COUNT": "3", "KMVIPE_SHARD_INDEX": "3"}, "set KMVIPE_SHARD_COUNT to the StatefulSet's replicas"),
    ({"KMVIPE_SHARD_COUNT": "2", "HOSTNAME": "mapstore-2"}, "not below KMVIPE_SHARD_COUNT=2"),
    ({"KMVIPE_SHARD_COUNT": "2", "HOSTNAME": "laptop"}, "set KMVIPE_SHARD_INDEX"),
    ({"KMVIPE_SHARD_COUNT": "2"}, "set KMVIPE_SHARD_INDEX"),
])
def test_bad_settings_are_refused_with_the_fix(env, settings, message):
    for var, value in settings.items():
        env.setenv(var, value)
    with pytest.raises(ValidationError, match=message):
        ShardSettings()


@pytest.mark.parametrize(("args", "error"), [
    (("cam0", 0, 0), ValueError), (("cam0", 2, 2), ValueError), (("cam0", -1, 2), ValueError),
    (("cam0", True, 2), ValueError), (("kmvipe/*", 0, 1), ConfigError),
])
def test_bad_arguments_are_refused(args, error):
    with pytest.raises(error):
        owns(*args)
