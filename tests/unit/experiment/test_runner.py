"""The runner's pure parts: profiles to netem impairments, and links switched on and off."""

from __future__ import annotations

import pytest

from arpz.experiment.runner import Links, _duration, impairments
from arpz.experiment.spec import PROFILES, NetworkProfile
from arpz.netem import Impairments


def test_profiles_become_impairments() -> None:
    imp = impairments(PROFILES["wifi-bad"])
    assert imp.loss == pytest.approx(0.03) and imp.delay_s == pytest.approx(0.005)
    assert imp.burst is not None and imp.burst.mean_loss == pytest.approx(0.013 / 0.263)
    assert imp.rate_bps == pytest.approx(54e6) and imp.jitter_s == 0
    assert impairments(PROFILES["lan"]) == Impairments()
    custom = impairments(NetworkProfile(loss_pct=20, jitter_ms=2))
    assert custom.loss == pytest.approx(0.2) and custom.jitter_s == pytest.approx(0.002)
    assert custom.burst is None


def test_links_are_clean_until_impaired_and_after_clear() -> None:
    links = Links.start("udp/127.0.0.1:9", {"robot1": PROFILES["wifi-bad"]}, seed=1)
    try:
        proxy = links.proxies["robot1"]
        assert links.endpoint("robot1") == f"udp/127.0.0.1:{proxy.listen_port}"
        assert proxy.up.imp == Impairments() and links.impaired_at is None
        links.impair()
        assert proxy.up.imp.loss > 0 and proxy.down.imp.loss > 0
        assert links.impaired_at is not None
        links.clear()
        assert proxy.up.imp == Impairments() and proxy.down.imp == Impairments()
    finally:
        totals = links.stop()
    assert totals == {"received": 0, "dropped": 0}


def test_eta_format() -> None:
    assert _duration(75) == "1m15s"
    assert _duration(3725) == "1h02m"
    assert _duration(-3) == "0m00s"
