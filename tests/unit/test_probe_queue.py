"""The sleep network's model of the queue the probes keep at the master (issue 28: "the sleep network charges the
same per-message time, so the two networks agree"): how much it holds, how long it takes to leave, who is told."""

from __future__ import annotations

import dataclasses
import math

import pandas as pd
import pytest

from nac_onboard.errors import BadInput
from nac_onboard.radio.channel import PRESETS
from nac_onboard.radio.medium import MacTiming, expected_message_s
from nac_onboard.radio.transfers import LinkNow, backlog_drain_s, probe_backlog_packets

WIFI = dataclasses.replace(PRESETS["wifi-flight"], mac="802.11")


def _link(phy_bps: float, in_range: bool = True) -> LinkNow:
    return LinkNow(10.0, 0.8 * phy_bps if in_range else 0.0, in_range, 0.0, phy_bps if in_range else 0.0)


def test_a_loss_based_tcp_keeps_three_quarters_of_the_queue_while_the_probes_run():
    assert probe_backlog_packets(1000, 2.0, 2.0, "reno") == 750
    assert probe_backlog_packets(1000, 4.0, 2.0, "cubic") == 750, "back to back is all the time, not more"
    assert probe_backlog_packets(1000, 0.5, 2.0, "reno") == pytest.approx(187.5), "a duty cycle of 25 %"
    assert probe_backlog_packets(1000, 2.0, 2.0, "bbr") == 0 and probe_backlog_packets(1000, 2.0, 2.0, "host") == 0


def test_the_backlog_leaves_at_each_links_rate_shared_equally_among_the_links_in_range():
    """Two links at one rate: each takes half, sent as the medium sends a message (aggregated exchanges), so the
    drain is two half-backlog messages; a slower link's half takes longer; a link out of range holds nothing, so
    the other takes it all; other networks' airtime stretches it; no backlog or no link: no wait."""
    fast, slow = 65e6, 6.5e6
    half = math.ceil(375 * 1500)
    both_fast = backlog_drain_s(WIFI, 750, [_link(fast), _link(fast)])
    assert both_fast == pytest.approx(2 * expected_message_s(MacTiming(), half, fast))
    bits = 750 * 1500 * 8
    assert bits / fast < both_fast < 1.2 * bits / fast, "the PHY's time and the medium's costs, a tenth of it"
    one_slow = backlog_drain_s(WIFI, 750, [_link(fast), _link(slow)])
    assert one_slow == pytest.approx(expected_message_s(MacTiming(), half, fast)
                                     + expected_message_s(MacTiming(), half, slow))
    assert one_slow > 4 * both_fast, "the slow link's half dominates: the FIFO is as slow as its slowest flow"
    alone = backlog_drain_s(WIFI, 750, [_link(fast), _link(slow, in_range=False)])
    assert alone == pytest.approx(expected_message_s(MacTiming(), 750 * 1500, fast))
    busy = dataclasses.replace(WIFI, background_airtime=0.25)
    assert backlog_drain_s(busy, 750, [_link(fast), _link(fast)]) == pytest.approx(both_fast / 0.75)
    assert backlog_drain_s(WIFI, 0, [_link(fast)]) == 0
    assert backlog_drain_s(WIFI, 750, [_link(fast, in_range=False)]) == 0
    efficiency = dataclasses.replace(WIFI, mac="efficiency")  # no PHY model: bits over each link's capacity
    assert backlog_drain_s(efficiency, 750, [_link(fast)]) == pytest.approx(750 * 1500 * 8 / (0.8 * fast))


def test_a_frame_level_air_scenario_on_the_sleep_network_models_the_probes_queue_and_says_so(tmp_path):
    from nac_onboard.compute.options import options_from_argv
    from sitl.experiment.commands import Ports, choose_network, compute_args, probe_backlog_args
    from sitl.experiment.scenario import load_scenario

    scenario = load_scenario("paper-flight-static")
    assert scenario.network.air == "medium" and scenario.network.congestion_control == "reno"
    def args_of(kernel: bool) -> list[str]:  # the run's channel file is the runner's: its preset here
        args = compute_args(scenario, tmp_path / "run", Ports(47000), 100.0, kernel=kernel)
        args[args.index("--channel") + 1] = "wifi-flight"
        return args

    args = args_of(kernel=False)
    assert args[args.index("--probe-backlog-packets") + 1] == "750"
    assert options_from_argv(args).probe_backlog_packets == 750
    kernel = args_of(kernel=True)
    assert "--probe-backlog-packets" not in kernel, "the kernel network's queue is its own"
    with pytest.raises(BadInput, match="--probe-backlog-packets models a queue for --emulate sleep"):
        options_from_argv([*kernel, "--probe-backlog-packets", "750"])
    for change in ({"air": "htb"}, {"congestion_control": "bbr"}):
        other = dataclasses.replace(scenario, network=dataclasses.replace(scenario.network, **change))
        assert probe_backlog_args(other) == [], change
    assert probe_backlog_args(dataclasses.replace(scenario, throughput=None)) == [], "no probes, no queue"
    network, why = choose_network("sleep", "medium", modelled_queue=True)
    assert network == "sleep" and "queue modelled, not run" in why and "no queues here" not in why
    assert "no queues here" in choose_network("sleep", "medium")[1]
    assert "queue" not in choose_network("sleep", "htb", modelled_queue=True)[1]


def test_a_blocks_modelled_wait_is_the_mean_of_its_iterations():
    from ground.logs.iteration_pace import modelled_wait_by_block

    blocks = pd.DataFrame({"first_iteration": [0, 10, 20]})
    waits = pd.Series({i: 0.1 * (i // 10 + 1) for i in range(25)})  # the third block lacks five iterations
    out = modelled_wait_by_block(blocks, waits)
    assert out[:2] == pytest.approx([0.1, 0.2]) and math.isnan(out[2])
