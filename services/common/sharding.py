"""Which replica of a stateful service serves which stream: shard ``index`` of ``count`` owns a stream.

Ownership is rendezvous (highest-random-weight) hashing: every shard scores the stream with a keyed BLAKE2b
digest of ``(stream, shard)`` and the highest score owns it (Thaler & Ravishankar, 1998). Three properties
follow, each held by tests/test_sharding.py:

- stable: the digest is the same in every process, host and Python version (``hash()`` is salted per process and
  would give each replica a different answer), so a restarted replica takes back exactly the streams it had;
- exactly one owner among ``count`` shards, about ``1/count`` of the streams each;
- minimal movement: going from N to N+1 shards moves only the streams the new shard wins (about 1/(N+1)), all to
  it; the other shards keep theirs (their durable maps stay where they are).

In Kubernetes a StatefulSet pod named ``mapstore-2`` is shard 2; ``KMVIPE_SHARD_COUNT`` is the replica count
(deploy/k8s, docs/DEPLOY.md). One process with no settings is shard 0 of 1 and owns every stream.
"""
from __future__ import annotations

import hashlib
import re

from pydantic import AliasChoices, Field, model_validator
from pydantic_settings import SettingsConfigDict

from .config_file import KmVipeSettings
from .keys import check_name

_DOMAIN = b"kmvipe-shard-v1"
"""Digest key: changing it (or the digest) reassigns every stream, so it is versioned and pinned by a test."""

_ORDINAL = re.compile(r"^[a-z0-9]([-a-z0-9.]*[a-z0-9])?-(?P<ordinal>0|[1-9][0-9]*)$")
"""A StatefulSet pod name: ``<statefulset>-<ordinal>`` (a DNS label, ordinals without leading zeros)."""


def _check_count(count: int) -> int:
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"shard count must be an integer >= 1 (the replica count), got {count!r}")
    return count


def _score(stream: str, shard: int) -> int:
    digest = hashlib.blake2b(f"{stream}/{shard}".encode(), digest_size=8, key=_DOMAIN).digest()
    return int.from_bytes(digest, "big")


def shard_of(stream: str, count: int) -> int:
    """Index in ``[0, count)`` of the shard that owns ``stream`` (a valid stream name, see :func:`keys.check_name`)."""
    check_name(stream)
    _check_count(count)
    # ties of two 64-bit digests are astronomically rare; the lower index wins them so the answer stays unique
    return max(range(count), key=lambda shard: (_score(stream, shard), -shard))


def owns(stream: str, shard: int, count: int) -> bool:
    """Whether shard ``shard`` of ``count`` serves ``stream``; exactly one shard of ``count`` does."""
    _check_count(count)
    if isinstance(shard, bool) or not isinstance(shard, int) or not 0 <= shard < count:
        raise ValueError(f"shard index must be an integer in [0, {count}) for {count} shard(s), got {shard!r}")
    return shard_of(stream, count) == shard


def ordinal_from_pod_name(name: str) -> int:
    """The ordinal of a StatefulSet pod name (``mapstore-2`` → 2); ValueError when ``name`` has none."""
    match = _ORDINAL.match(name.strip())
    if match is None:
        raise ValueError(
            f"cannot take a shard index from pod name {name!r} (KMVIPE_SHARD_POD_NAME, else $HOSTNAME): a "
            "StatefulSet pod is named <statefulset>-<ordinal> (e.g. mapstore-2); set KMVIPE_SHARD_INDEX, or run as a "
            "StatefulSet pod"
        )
    return int(match["ordinal"])


class ShardSettings(KmVipeSettings):
    """Which shard this process is (env prefix ``KMVIPE_SHARD_``); :attr:`index` is resolved on construction."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_SHARD_", env_file=".env", extra="ignore",
                                      populate_by_name=True)

    count: int = Field(1, ge=1)
    """Number of replicas that split the streams (a StatefulSet's ``replicas``); 1: this process owns every stream."""
    index: int | None = Field(None, ge=0)
    """This replica's shard in ``[0, count)``. Unset: the ordinal of :attr:`pod_name` when ``count`` > 1, else 0."""
    pod_name: str = Field("", validation_alias=AliasChoices("KMVIPE_SHARD_POD_NAME", "HOSTNAME"))
    """The pod's name (the downward API's ``metadata.name``; falls back to ``$HOSTNAME``, which Kubernetes sets to
    the pod name), read only when :attr:`index` is unset and ``count`` > 1."""

    @model_validator(mode="after")
    def _resolve_index(self) -> ShardSettings:
        if self.index is None:
            # one replica owns everything whatever the host is called (a laptop named "box-3" is still shard 0)
            self.index = ordinal_from_pod_name(self.pod_name) if self.count > 1 else 0
        if self.index >= self.count:
            raise ValueError(
                f"shard index {self.index} is not below KMVIPE_SHARD_COUNT={self.count}: set KMVIPE_SHARD_COUNT to "
                "the StatefulSet's replicas (every replica the same), or KMVIPE_SHARD_INDEX below it"
            )
        return self

    def owns(self, stream: str) -> bool:
        """Whether this replica serves ``stream``."""
        return owns(stream, self.index, self.count)
