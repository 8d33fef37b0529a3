"""The configuration against the DAQ's DESCRIPTOR: missing and mismatched channels are named."""

from __future__ import annotations

import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import check_against_descriptor, demo_config, load_config_text
from millsense.drivers.protocol import Channel, ChannelKind, Descriptor
from tests.config.helpers import base, dumps

pytestmark = pytest.mark.quick

K = ChannelKind
SIM = [("v_uv", K.VOLTAGE), ("v_vw", K.VOLTAGE), ("v_wu", K.VOLTAGE), ("i_u", K.CURRENT), ("i_v", K.CURRENT),
       ("i_w", K.CURRENT), ("sp_rpm", K.SPEED), ("sp_enc", K.ENCODER)]


def descriptor(pairs) -> Descriptor:
    return Descriptor(sample_rate_hz=1000, channels=tuple(Channel(kind=k, name=n) for n, k in pairs))


def test_the_demo_fits_the_simulated_daq():
    assert check_against_descriptor(demo_config(), descriptor(SIM)) == []


def test_a_channel_the_daq_does_not_send_is_named_with_what_it_sends():
    pairs = [p for p in SIM if p[0] != "i_w"]
    problems = check_against_descriptor(demo_config(), descriptor(pairs), raise_on_problems=False)
    assert problems == [
        "channels.i_w: the DAQ does not send this channel (it sends: v_uv (voltage), v_vw (voltage), v_wu (voltage), "
        "i_u (current), i_v (current), sp_rpm (speed), sp_enc (encoder))"
    ]
    with pytest.raises(ConfigError) as info:
        check_against_descriptor(demo_config(), descriptor(pairs))
    assert info.value.problems == problems


def test_mismatched_kinds_and_too_few_power_channels():
    pairs = [(n, K.CURRENT if n.startswith("v_") else k) for n, k in SIM]  # voltages announced as currents
    problems = check_against_descriptor(demo_config(), [(n, int(k)) for n, k in pairs], raise_on_problems=False)
    assert problems[:3] == [
        f"channels.{n}: the DAQ says it is a current channel (by its name, a voltage channel: check the wiring or the name)"
        for n in ("v_uv", "v_vw", "v_wu")
    ]
    assert problems[3].startswith("channels: the power ([P] eq. 11) needs at least 2 line voltages")
    assert len(problems) == 4


def test_encoder_needs_counts_per_rev_and_feed_drive_a_feed_current():
    doc = base()
    del doc["channels"]["sp_enc"]["counts_per_rev"]
    doc["channels"]["ix_feed"] = {"scale": 0.001}
    doc["feed_force"] = {"ix_feed": {"newton_per_amp": 950.0}}
    doc["depth"]["method"] = "feed-drive"
    s = load_config_text(dumps(doc))
    pairs = {**dict(SIM), "ix_feed": K.FEED_RATE}
    problems = check_against_descriptor(s, pairs, raise_on_problems=False)
    assert problems == [
        "channels.sp_enc.counts_per_rev: missing (an encoder channel needs counts per spindle revolution, e.g. 4096)",
        "channels.ix_feed: the DAQ says it is a feed_rate channel (by its name, a feed_current channel: check the wiring or the name)",
        "feed_force.ix_feed: the DAQ says ix_feed is a feed_rate channel (a feed_current channel)",
        'depth.method: "feed-drive" needs a feed_current channel with a [feed_force] entry, configured and sent',
    ]
    pairs["ix_feed"] = K.FEED_CURRENT
    doc["channels"]["sp_enc"]["counts_per_rev"] = 4096
    assert check_against_descriptor(load_config_text(dumps(doc)), pairs) == []


def test_dynamometer_needs_two_force_channels_sent():
    doc = base()
    doc["depth"]["method"] = "dynamometer"
    doc["channels"].update(fx={"scale": 0.5}, fy={"scale": 0.5})
    s = load_config_text(dumps(doc))
    problems = check_against_descriptor(s, SIM + [("fx", K.FORCE)], raise_on_problems=False)
    assert problems[0].startswith("channels.fy: the DAQ does not send this channel")
    assert problems[1] == 'depth.method: "dynamometer" needs two force channels configured and sent; found fx'
    assert check_against_descriptor(s, SIM + [("fx", K.FORCE), ("fy", K.FORCE)]) == []
