"""Bad payloads for robustness tests: random bytes, truncated and bit-flipped valid messages, and well-formed
msgpack with wrong fields."""
from __future__ import annotations

import random
from typing import Iterator

from services.common import codec, schema


def bad_payloads(valid: list[bytes], count: int, seed: int = 0) -> Iterator[bytes]:
    rng = random.Random(seed)
    kinds = list(schema.MESSAGES)
    for i in range(count):
        base = rng.choice(valid)
        mode = i % 4
        if mode == 0:
            yield rng.randbytes(rng.randint(0, 300))
        elif mode == 1:
            yield base[: rng.randint(0, len(base) - 1)]
        elif mode == 2:
            flipped = bytearray(base)
            for _ in range(rng.randint(1, 8)):
                flipped[rng.randrange(len(flipped))] = rng.randrange(256)
            yield bytes(flipped)
        else:
            yield codec.pack({"kind": rng.choice(kinds), "v": 1, "stream": "s", "seq": rng.randint(-5, 5),
                              "t_ns": 0, "image": rng.randbytes(10), "consumer": rng.randint(0, 3)})
