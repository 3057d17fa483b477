"""A downstream stage for tests, in its own process: takes frames (slowly if asked), grants credit, records
what arrived, and writes it as JSON at end of stream.

usage: python -m tests.helpers.frame_consumer ENDPOINT STREAM OUT_JSON [--delay S] [--window N] [--listen]
"""
from __future__ import annotations

import argparse
import json
import threading
import time

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.schema import Credit, Eos, Frame


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("endpoint")
    ap.add_argument("stream")
    ap.add_argument("out")
    ap.add_argument("--delay", type=float, default=0.0)
    ap.add_argument("--window", type=int, default=4)
    ap.add_argument("--listen", action="store_true")
    args = ap.parse_args()
    where = {"listen": [args.endpoint]} if args.listen else {"connect": [args.endpoint]}
    with Bus(BusSettings(mode="peer", **where), "features", "test-consumer") as bus:
        inbox = bus.inbox({keys.topic(args.stream, keys.FRAME): [Frame], keys.topic(args.stream, keys.EOS): [Eos]})
        credit_key = keys.topic(args.stream, keys.CREDIT)
        last = -1
        stop = threading.Event()

        def heartbeat() -> None:  # keep granting even while busy, as the features service does
            while not stop.is_set():
                bus.publish(credit_key, Credit(args.stream, last + args.window, time.time_ns(), consumer="test"))
                stop.wait(0.05)

        threading.Thread(target=heartbeat, daemon=True).start()
        bus.ready()
        open(args.out + ".ready", "w").close()  # subscribed: the test may start the producer
        seqs, eos = [], None
        # Zenoh orders per key only: the EOS may overtake the last frames, so read on until its count arrived
        while eos is None or len(seqs) < eos.count:
            delivery = inbox.get(timeout=60 if eos is None else 10)
            if delivery is None:
                break
            if isinstance(delivery.msg, Eos):
                eos = delivery.msg
                continue
            seqs.append(delivery.msg.seq)
            time.sleep(args.delay)  # a slow stage
            last = delivery.msg.seq
        stop.set()
        if eos is not None:  # as features does: the source may stop holding the stream for a restart of ours
            bus.publish(keys.topic(args.stream, keys.EOS), Eos(args.stream, eos.seq, time.time_ns(), stage="features",
                                                              count=len(seqs)))
        result = {"seqs": seqs, "eos": None if eos is None else {"seq": eos.seq, "count": eos.count},
                  "inbox_dropped": inbox.dropped, "bad_payloads": bus.stats.total}
    with open(args.out, "w") as f:
        json.dump(result, f)


if __name__ == "__main__":
    main()
