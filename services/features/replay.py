"""What features sent to ba (and to the mapstore) since their durable point, sent again when one resumes from it.

ba checkpoints its mapping state now and then (services/ba/checkpoint.py) and says in its progress reports up to
which frame seq the newest checkpoint holds (``durable``). A ba killed and restarted resumes from that checkpoint
under a new consumer name and reports the checkpoint's seq; everything features sent after it — keyframes, frame
messages, codes, its end of stream — would be lost, since Zenoh delivers to whoever subscribed at the time. So
features keeps those messages (bounded: ``max_messages``; beyond it the oldest are given up and counted) and, when
a ba consumer it has not heard from before reports after another one did, publishes them again in their original
order. Nothing is kept while no ba checkpoints. Codes are kept apart from frames: a keyframe's codes come after
it, possibly after the checkpoint that holds the keyframe, so the newest ``max_codes`` codes are always resent
(ba takes a repeated one as the same codes again).

The mapstore works the same way with its database as the checkpoint: its progress (the highest keyframe it
committed) is durable by construction, and a restarted mapstore reports it under a new name; features then sends
it again the keyframes after it and the newest codes."""
from __future__ import annotations

import logging
import threading
from collections import deque

from ..common import keys
from ..common.restarts import Restarts
from ..common.schema import Credit, Eos, FrameLite, Keyframe, KeyframeCodes, Message

log = logging.getLogger(__name__)


class ReplayBuffer:
    """What features sent to the consumers named ``prefix`` (``ba-``, ``mapstore-``) after their durable point:
    messages of ``kinds`` (and features' end of stream with ``eos``) in send order, the newest codes apart."""

    def __init__(self, prefix: str = "ba-", kinds: tuple[type[Message], ...] = (Keyframe, FrameLite),
                 eos: bool = True, max_messages: int = 512, max_codes: int = 64):
        self.prefix, self.kinds, self.eos = prefix, kinds, eos
        self.max_messages = max_messages
        self._frames: deque[tuple[str, Message]] = deque()  # kinds (and the EOS), in send order
        self._codes: deque[tuple[str, Message]] = deque(maxlen=max_codes)
        self._lock = threading.Lock()
        self._restarts = Restarts(prefix)
        self._resume_after: int | None = None  # a new instance resumed after this seq: replay on the loop
        self.active = False  # such a consumer keeps durable state (a checkpoint, a database)
        self.finished = False  # it sent its end of stream: nothing more to keep
        self.durable = -1
        self.given_up = 0  # messages dropped from a full buffer (a consumer restarting later misses them)
        self.replayed = 0

    def on_progress(self, msg: Credit) -> list[str]:
        """A downstream progress report (Zenoh thread). Returns the consumers it replaces (gone: a new one
        resumed), for the caller to forget."""
        if not msg.consumer.startswith(self.prefix) or not msg.checkpoints:
            return []
        replaced = self._restarts.replaced_by(msg.consumer)
        with self._lock:
            self.active = True
            if replaced:  # it resumed from its durable state: what came after it is due again
                # from its predecessor's durable point too: a message sent while none was up, then one the new
                # instance got live before its first report, put that report past a gap (the repeats are
                # recognised downstream); the floor stays the durable point until the replay has gone out
                floor = min(msg.seq, self.durable)
                self._resume_after, self.durable = floor, floor
            else:
                self.durable = max(self.durable, msg.durable)
            return replaced

    def record(self, key: str, msg: Message) -> None:
        """A message features published (loop thread)."""
        if not self.active:
            return
        with self._lock:
            if isinstance(msg, KeyframeCodes):
                self._codes.append((key, msg))
                return
            if not isinstance(msg, self.kinds) and not (self.eos and isinstance(msg, Eos) and key.endswith(keys.EOS)):
                return
            self._frames.append((key, msg))
            while self._frames and (self._frames[0][1].seq <= self.durable and
                                    not isinstance(self._frames[0][1], Eos)):
                self._frames.popleft()
            while len(self._frames) > self.max_messages:
                self._frames.popleft()
                self.given_up += 1

    def due(self) -> list[tuple[str, Message]]:
        """The messages to publish again now (loop thread): after a ba resumed, what it has not got."""
        with self._lock:
            after, self._resume_after = self._resume_after, None
            if after is None:
                return []
            frames = [(k, m) for k, m in self._frames if m.seq > after or isinstance(m, Eos)]
            out = frames + list(self._codes)
        self.replayed += len(out)
        log.info("a consumer resumed from its durable state: sending again what came after it", extra={
            "consumer": self.prefix.rstrip("-"), "after_seq": after, "messages": len(out), "given_up": self.given_up})
        return out
