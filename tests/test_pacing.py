"""Credit ledger and send/wait/drop decisions (pure logic, time passed in)."""
from services.ingest.core.pacing import CreditLedger, Decision, decide


def test_no_consumer_means_nothing_may_be_sent():
    assert CreditLedger(ttl_s=5).limit(now=0.0) == -1


def test_slowest_live_consumer_sets_the_limit():
    ledger = CreditLedger(ttl_s=5)
    ledger.grant("a", 10, now=0.0)
    ledger.grant("b", 4, now=0.0)
    assert ledger.limit(now=1.0) == 4


def test_grants_never_go_backwards():
    ledger = CreditLedger(ttl_s=5)
    ledger.grant("a", 10, now=0.0)
    ledger.grant("a", 3, now=0.5)  # a late, reordered credit message
    assert ledger.limit(now=1.0) == 10


def test_silent_consumer_expires():
    ledger = CreditLedger(ttl_s=5)
    ledger.grant("dead", 2, now=0.0)
    ledger.grant("live", 50, now=4.0)
    assert ledger.limit(now=4.5) == 2
    assert ledger.limit(now=6.0) == 50


def test_decisions():
    assert decide(3, limit=3, lossless=True) is Decision.SEND
    assert decide(4, limit=3, lossless=True) is Decision.WAIT
    assert decide(4, limit=3, lossless=False) is Decision.DROP
