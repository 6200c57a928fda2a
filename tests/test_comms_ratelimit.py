"""The flood summarizer: one report per cause per period, the tail reported, memory bounded."""

from __future__ import annotations

from comms.ratelimit import OTHER, Summarizer


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_a_flood_of_900_per_second_gives_one_report_per_second_per_cause():
    clock = Clock()
    s = Summarizer(period_s=1.0, clock_s=clock)
    reports = []
    for k in range(2700):  # 3 s at 900/s, two causes
        clock.t = k / 900
        for cause in ("unsigned command", "bad signature"):
            r = s.hit(cause)
            if r is not None:
                reports.append(r)
        reports += s.due()
    clock.t = 4.0
    reports += s.due()  # the tail of the flood
    for cause in ("unsigned command", "bad signature"):
        mine = [r for r in reports if r.cause == cause]
        assert 3 <= len(mine) <= 5
        assert sum(r.count for r in mine) == 2700
    assert s.total == 5400
    clock.t = 5.5
    assert s.due() == []
    assert s.hit("unsigned command").count == 1  # quiet for a period: reported at once again


def test_causes_are_bounded():
    s = Summarizer(max_causes=3, clock_s=Clock())
    for k in range(100):
        s.hit(f"cause {k}")
    assert len(s._since) <= 4 and OTHER in s._since
