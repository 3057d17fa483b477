"""The stream host (services/common/streams.py) on a real loopback bus: a worker per announced stream, only the
streams its shard owns, released once the source is gone and the worker sent its end of stream, at most
max_streams at once."""
from __future__ import annotations

import threading

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.schema import Eos
from services.common.sharding import ShardSettings, owns
from services.common.streams import StreamHost
from tests.conftest import wait_until

STREAMS = [f"cam{i}" for i in range(8)]


class Workers:
    """A worker per stream that sends its EOS when told to, and records what it ran for."""

    def __init__(self):
        self.started: list[str] = []
        self.finish = {s: threading.Event() for s in STREAMS}

    def __call__(self, stream, scope, stop) -> None:
        self.started.append(stream)
        scope.subscribe(keys.topic(stream, keys.FRAME), lambda d: None)
        while not stop.wait(0.02):
            if self.finish[stream].is_set():
                scope.publish(keys.topic(stream, keys.EOS), Eos(stream, 0, 0, stage="test"))
                self.finish[stream].clear()


def test_each_shard_serves_the_streams_it_owns_and_releases_finished_ones(tcp_endpoint):
    peer = BusSettings(mode="peer", listen=[tcp_endpoint])
    client = BusSettings(mode="client", connect=[tcp_endpoint])
    with Bus(peer, "source") as source, Bus(client, "mapstore") as one, Bus(client, "mapstore") as two:
        workers = [Workers(), Workers()]
        hosts = [StreamHost(bus, w, ShardSettings(count=2, index=i), idle_s=30, linger_s=0.2)
                 for i, (bus, w) in enumerate(zip((one, two), workers))]
        stop = threading.Event()
        threads = [threading.Thread(target=h.run, args=(stop,), daemon=True) for h in hosts]
        for t in threads:
            t.start()
        tokens = {s: source.announce(s) for s in STREAMS}
        try:
            wait_until(lambda: sum(len(h.served) for h in hosts) == len(STREAMS), 30, "every stream served")
            for i, host in enumerate(hosts):
                assert set(host.served) == {s for s in STREAMS if owns(s, i, 2)}  # each stream exactly once
            tokens.pop("cam0").undeclare()  # its source is gone, but the worker has not finished: kept
            owner = hosts[0] if "cam0" in hosts[0].served else hosts[1]
            stop.wait(0.5)
            assert "cam0" in owner.served
            workers[hosts.index(owner)].finish["cam0"].set()  # it sends its end of stream: released
            wait_until(lambda: "cam0" not in owner.served, 5, "cam0 released")
            tokens["cam0"] = source.announce("cam0")  # the same stream again: a new worker
            wait_until(lambda: "cam0" in owner.served, 5, "cam0 served again")
            # the host serves it once its thread is started; the worker records itself when that thread runs
            wait_until(lambda: workers[hosts.index(owner)].started.count("cam0") == 2, 5, "cam0's second worker")
        finally:
            stop.set()
            for t in threads:
                t.join(timeout=10)
            for token in tokens.values():
                token.undeclare()
        assert all(not h.served for h in hosts)  # stopping the host stops every worker


def test_a_host_at_its_maximum_refuses_more_streams_until_one_is_released(tcp_endpoint):
    with Bus(BusSettings(mode="peer", listen=[tcp_endpoint]), "source") as source, \
            Bus(BusSettings(mode="client", connect=[tcp_endpoint]), "ba") as bus:
        workers = Workers()
        host = StreamHost(bus, workers, idle_s=30, max_streams=2, linger_s=0.2)
        stop = threading.Event()
        thread = threading.Thread(target=host.run, args=(stop,), daemon=True)
        thread.start()
        tokens = [source.announce(s) for s in STREAMS[:3]]
        try:
            wait_until(lambda: len(host.served) == 2 and len(host.refused) == 1, 30, "two served, one refused")
            refused = next(iter(host.refused))
            first = next(iter(host.served))
            tokens[STREAMS.index(first)].undeclare()
            workers.finish[first].set()
            wait_until(lambda: refused in host.served, 10, "the refused stream served once there is room")
        finally:
            stop.set()
            thread.join(timeout=10)
            for token in tokens:
                try:
                    token.undeclare()
                except Exception:  # noqa: BLE001 (already undeclared above)
                    pass


def test_a_kept_finished_stream_stays_until_a_new_one_needs_its_place(tcp_endpoint):
    """The mapstore keeps a finished camera's map answering queries; only a new stream beyond max_streams takes
    its place, and then the finished one that was quiet longest goes."""
    with Bus(BusSettings(mode="peer", listen=[tcp_endpoint]), "source") as source, \
            Bus(BusSettings(mode="client", connect=[tcp_endpoint]), "mapstore") as bus:
        workers = Workers()
        host = StreamHost(bus, workers, idle_s=0.1, max_streams=2, linger_s=None)
        stop = threading.Event()
        thread = threading.Thread(target=host.run, args=(stop,), daemon=True)
        thread.start()
        tokens = {s: source.announce(s) for s in STREAMS[:2]}
        try:
            wait_until(lambda: len(host.served) == 2, 30, "two served")
            for s in STREAMS[:2]:
                tokens.pop(s).undeclare()
            workers.finish[STREAMS[0]].set()
            stop.wait(1.0)
            assert set(host.served) == set(STREAMS[:2])  # finished and idle, yet kept
            tokens[STREAMS[2]] = source.announce(STREAMS[2])
            wait_until(lambda: STREAMS[2] in host.served, 30, "the new stream served")
            assert set(host.served) == {STREAMS[1], STREAMS[2]}  # the finished one made room, not the other
        finally:
            stop.set()
            thread.join(timeout=10)
            for token in tokens.values():
                token.undeclare()
