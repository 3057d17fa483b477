"""The pace of a loop's periodic work (services.common.lifecycle.Period): the mapstore's re-fusion is due at most
once per refresh_period_s, and a slow one holds the next back (refresh_max_share)."""
from __future__ import annotations

from services.common.lifecycle import Period


def test_the_loop_refreshes_at_most_once_per_period():
    now = [0.0]
    pace = Period(2.0, clock=lambda: now[0])
    assert not pace.due()  # the period starts with the loop
    now[0] = 2.0
    assert pace.due() and not pace.due()  # due once, then the period starts again
    now[0] = 3.9
    assert not pace.due()
    now[0] = 4.0
    assert pace.due()
    always = Period(0.0, clock=lambda: now[0])
    assert always.due() and always.due()  # 0: after every batch


def test_a_slow_re_fusion_holds_the_next_one_back():
    """refresh_max_share: a re-fusion that took 3 s at a third of the time is followed by 6 s without one; a quick
    one leaves the period as it was."""
    now = [0.0]
    pace = Period(2.0, clock=lambda: now[0])
    now[0] = 2.0
    assert pace.due()
    now[0] = 5.0  # the re-fusion took 3 s
    pace.hold_after(3.0, 0.34)
    now[0] = 10.8
    assert not pace.due()
    now[0] = 10.9
    assert pace.due()
    now[0] = 11.0  # 0.1 s: 0.19 s held, within the period
    pace.hold_after(0.1, 0.34)
    now[0] = 12.8
    assert not pace.due()
    now[0] = 12.9
    assert pace.due()
    always = Period(0.0, clock=lambda: now[0])
    always.hold(1.0)
    assert not always.due()
    now[0] = 14.0
    assert always.due() and always.due()
