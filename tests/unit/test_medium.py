"""The Wi-Fi medium frame by frame (nac_onboard.radio.medium): the standard's timing, FIFO queues, aggregation,
contention, retries. Seeded: every count below is the same on every run; the bounds on random outcomes are several
standard deviations of their binomial laws, stated where they are used."""

import numpy as np
import pytest

from nac_onboard.radio.medium import BROADCAST, MacTiming, Medium, expected_echo_s, expected_message_s

T = MacTiming()


def medium(stations: int, rate_bps: float, per: float = 0.0, **kwargs) -> Medium:
    m = Medium(stations, **kwargs)
    m.set_links(np.full((stations, stations), rate_bps), np.full((stations, stations), per))
    return m


def test_the_timing_is_the_standards():
    """AIFS[BE] = SIFS + 3 slots; a 1,500-byte packet at MCS 7 (65 Mbit/s): 36 us of HT preamble, 48 symbols of
    4 us for its 1,544 bytes with headers, delimiter and padding, and the 6 us signal extension."""
    assert T.aifs_s == pytest.approx(37e-6)
    assert T.subframe_bytes(1500) == 1544
    assert T.ppdu_s(1544, 65e6) == pytest.approx(36e-6 + 48 * 4e-6 + 6e-6)
    assert T.block_ack_s() == pytest.approx(20e-6 + 3 * 4e-6 + 6e-6)  # 32 bytes at 24 Mbit/s: 3 symbols


def test_a_lone_small_frame_costs_a_quarter_of_a_millisecond_not_microseconds():
    """One 100-byte message on an idle medium at 30 Mbit/s: delivered after AIFS, 0-15 slots of backoff and its
    PPDU, as the closed form says on average."""
    m = medium(2, 30e6)
    m.offer(0.0, 0, 1, 100, "hello")
    (delivery,) = m.run_until(1.0)
    ppdu = T.ppdu_s(T.subframe_bytes(100), 30e6)
    assert T.aifs_s + ppdu <= delivery.delivered_s <= T.aifs_s + 15 * T.slot_s + ppdu + 1e-12
    assert delivery.dst == 1 and delivery.frame.item == "hello"
    assert expected_message_s(T, 100, 30e6) == pytest.approx(0.5 * T.slot_s + 7.5 * T.slot_s + ppdu)


def test_the_closed_form_is_what_the_medium_charges_a_message_after_idle_air():
    """2,000 lone messages, each 20 ms after the last (the medium idle for AIFS and more): their mean time to the
    receiver is the closed form's, small and large. The backoff is uniform over 16 slots (standard deviation 41 us),
    so the mean of 2,000 is within 3 us of its expectation with probability above 0.999 (3.3 standard errors);
    the bound is 5 us."""
    for size_bytes in (100, 20_000):
        m = medium(2, 30e6)
        t_s, waits = 1.0, []
        for _ in range(2000):
            for packet_bytes in [1500] * (size_bytes // 1500) + [size_bytes % 1500]:
                m.offer(t_s, 0, 1, packet_bytes)
            waits.append(max(d.delivered_s for d in m.run_until(t_s + 0.019)) - t_s)
            t_s += 0.02
        assert abs(sum(waits) / len(waits) - expected_message_s(T, size_bytes, 30e6)) < 5e-6, size_bytes


def test_an_echo_answered_at_once_pays_the_requests_block_ack_before_its_reply():
    """2,000 echoes of 100 bytes, each 20 ms after the last, the reply offered the moment the request is delivered:
    their mean round trip is the closed form's, a block ack and AIFS above two lone messages. Two uniform backoffs
    of 16 slots (standard deviation 58 us together): the mean of 2,000 is within 4.3 us of its expectation with
    probability above 0.999; the bound is 5 us."""
    m = medium(2, 30e6)
    t_s, round_trips = 1.0, []
    for _ in range(2000):
        m.offer(t_s, 0, 1, 100)
        (request,) = m.run_until(t_s + 0.009)
        m.offer(request.delivered_s, 1, 0, 100)
        (reply,) = m.run_until(t_s + 0.019)
        round_trips.append(reply.delivered_s - t_s)
        t_s += 0.02
    assert abs(sum(round_trips) / len(round_trips) - expected_echo_s(T, 100, 30e6)) < 5e-6
    assert expected_echo_s(T, 100, 30e6) - 2 * expected_message_s(T, 100, 30e6) > T.block_ack_s() + T.aifs_s - T.slot_s


def test_a_small_message_waits_behind_the_bulk_its_station_queued_first():
    """First in, first out: 999 packets of a bulk transfer, then a 100-byte message; it leaves last, after the
    bulk's whole air time (about 0.43 s at 30 Mbit/s), and every packet arrives in order."""
    m = medium(2, 30e6)
    for k in range(999):
        m.offer(0.0, 0, 1, 1500, k)
    m.offer(0.0, 0, 1, 100, "small")
    delivered = m.run_until(10.0)
    assert [d.frame.item for d in delivered] == [*range(999), "small"]
    assert delivered[-1].queue_s > 0.4 and m.stats.queue_drops == 0


def test_a_full_queue_drops_the_tail_and_counts_it():
    m = medium(2, 30e6, queue_packets=10)
    accepted = [m.offer(0.0, 0, 1, 1500, k) for k in range(15)]
    assert accepted == [True] * 10 + [False] * 5 and m.stats.queue_drops == 5
    assert [d.frame.item for d in m.run_until(1.0)] == list(range(10))
    with pytest.raises(ValueError, match="queue_packets"):
        Medium(2, queue_packets=0)


@pytest.mark.parametrize("rate_bps", [6.5e6, 65e6])
def test_saturated_goodput_is_what_aggregation_and_the_timing_allow(rate_bps):
    """20,000 packets back to back: the frame-by-frame medium carries what the closed form says (aggregates of up
    to 4 ms, each paying access, preamble and block ack), within 1 % (the backoff draws average out over the
    aggregates: at least 400 of them). At 65 Mbit/s that is about 60 Mbit/s, at 6.5 Mbit/s about 6."""
    m = medium(2, rate_bps, queue_packets=20_000)
    for _ in range(20_000):
        m.offer(0.0, 0, 1, 1500)
    delivered = m.run_until(100.0)
    goodput = 20_000 * 1500 * 8 / delivered[-1].delivered_s
    assert goodput == pytest.approx(20_000 * 1500 * 8 / expected_message_s(T, 20_000 * 1500, rate_bps), rel=0.01)
    assert 0.85 * rate_bps < goodput < 0.95 * rate_bps


@pytest.mark.parametrize("rate_bps", [1e6, 6.5e6, 24e6, 30e6, 58.5e6, 65e6])
def test_an_aggregate_holds_the_most_subframes_within_4_ms_and_no_more(rate_bps):
    """The aggregate's airtime limit as bytes (worked out once a rate): the most a PPDU carries within 4 ms by
    ppdu_s itself, so an aggregate of packets of one size takes as many as fit and one more would not."""
    m = medium(2, rate_bps, queue_packets=200)
    most = m._ppdu_bytes_within(rate_bps)
    assert T.ppdu_s(most, rate_bps) <= T.max_ppdu_s < T.ppdu_s(most + 1, rate_bps)
    for _ in range(200):
        m.offer(0.0, 0, 1, 300)
    m.run_until(m.next_event_s())  # the first exchange starts
    sub = T.subframe_bytes(300)
    sent = 200 - m.backlog(0)
    expected = min(T.max_ampdu_frames, T.max_ampdu_bytes // sub, max(most // sub, 1))
    assert sent == expected and T.ppdu_s(sent * sub, rate_bps) <= max(T.max_ppdu_s, T.ppdu_s(sub, rate_bps))


def test_two_saturated_stations_share_the_air_and_sometimes_collide():
    """Two stations sending to a third: each gets half the frames (within 5 %), and some exchanges collide: with
    both drawing from 16 slots, about 1 in 16 (Bianchi's model for 2 stations); here between 2 % and 15 %."""
    m = medium(3, 65e6, queue_packets=100_000, seed=1)
    for _ in range(20_000):
        m.offer(0.0, 0, 2, 1500)
        m.offer(0.0, 1, 2, 1500)
    delivered = m.run_until(2.0)
    share = sum(d.frame.src == 0 for d in delivered) / len(delivered)
    assert share == pytest.approx(0.5, abs=0.05)
    assert 0.02 < m.stats.collisions / m.stats.exchanges < 0.15


def test_frame_errors_are_retried_and_only_the_exhausted_are_lost():
    """A frame error rate of 0.5 and 7 retries: a packet is lost when all 8 tries fail, 0.5^8 of 20,000 = 78 on
    average (binomial standard deviation 8.8; the bound is 4 of them), and nothing is lost without errors."""
    m = medium(2, 30e6, per=0.5, queue_packets=20_000, seed=3)
    for _ in range(20_000):
        m.offer(0.0, 0, 1, 1500)
    delivered = m.run_until(100.0)
    assert abs(m.stats.retry_drops - 78.1) < 4 * 8.8
    assert len(delivered) + m.stats.retry_drops == 20_000


def test_out_of_range_every_try_fails_and_still_costs_air():
    m = medium(2, 0.0)
    m.offer(0.0, 0, 1, 1500)
    assert m.run_until(1.0) == [] and m.stats.retry_drops == 1
    assert m.stats.exchanges == 8 and m.stats.busy_s > 8 * T.ppdu_s(1544, T.control_rate_bps)


def test_a_broadcast_goes_once_at_the_basic_rate_to_every_station_in_range():
    m = Medium(3)
    rates = np.full((3, 3), 30e6)
    rates[0, 2] = 0.0  # station 2 is out of station 0's range
    m.set_links(rates, np.zeros((3, 3)))
    m.offer(0.0, 0, BROADCAST, 200, "state")
    delivered = m.run_until(1.0)
    assert [d.dst for d in delivered] == [1] and m.stats.exchanges == 1
    assert delivered[0].delivered_s > T.ppdu_s(T.subframe_bytes(200), T.broadcast_rate_bps, T.legacy_preamble_s)


def test_a_broadcast_is_lost_with_the_slowest_rates_error_rate_not_the_data_rates():
    """A group frame goes at the basic rate with no retries: near the range edge, where the pair's data rate loses
    most frames (0.9 here) and MCS 0 few (0.1), about 9 of 10 broadcasts arrive. 1,000 of them: 900 expected,
    standard deviation 9.5, so the bounds are 5 standard deviations each side; a data-rate loss gives about 100."""
    m = Medium(2)
    rates = np.full((2, 2), 30e6)
    m.set_links(rates, np.full((2, 2), 0.9), np.full((2, 2), 6.5e6), np.full((2, 2), 0.1))
    for k in range(1000):
        m.offer(k * 0.01, 0, BROADCAST, 200, k)
    assert 850 < len(m.run_until(20.0)) < 950


def test_a_segmentation_offload_run_costs_the_air_of_its_packets_and_their_room_in_the_queue():
    """Linux hands a TUN device 64 KB of a TCP flow at once (TSO): as 44 packets of 1,500 bytes it takes the same
    air time as 44 separate packets (three aggregates of at most 4 ms), and 44 places of the queue."""
    single, run = medium(2, 65e6, seed=5), medium(2, 65e6, seed=5)
    for k in range(44):
        single.offer(0.0, 0, 1, 1500, k)
    run.offer(0.0, 0, 1, 44 * 1500, "run", segments=44)
    assert run.backlog(0) == single.backlog(0) == 44
    last_single = single.run_until(1.0)[-1].delivered_s
    (delivered,) = run.run_until(1.0)
    assert delivered.delivered_s == pytest.approx(last_single) and run.stats.exchanges == single.stats.exchanges == 3


def test_a_full_queue_drops_a_runs_tail_packet_by_packet():
    """A queue of 50 packets holding a 44-segment run has room for 6 of a 10-segment run: those 6 are queued and
    sent, its last 4 are dropped and counted (delivered as the run's lost segments, which the delay line cuts out),
    and a single packet after it finds no room. A whole-run drop would have kept the queue 6 short, room that a
    stack batching fewer segments (a slower speed-up) would have filled: what is dropped would depend on batching."""
    full = medium(2, 65e6, queue_packets=50)
    assert full.offer(0.0, 0, 1, 44 * 1500, "first", segments=44)
    assert full.offer(0.0, 0, 1, 10 * 1500, "second", segments=10) and full.backlog(0) == 50
    assert not full.offer(0.0, 0, 1, 100, "third") and full.stats.queue_drops == 5
    first, second = full.run_until(1.0)
    assert (first.frame.item, first.lost_segments) == ("first", ())
    assert (second.frame.item, second.lost_segments) == ("second", (6, 7, 8, 9))
    assert full.stats.segments_delivered == 50 and full.stats.retry_drops == 0 and full.backlog(0) == 0


def test_a_run_loses_only_the_segments_that_failed_every_try():
    """On the air each segment of an offload run is its own MPDU, retried on its own: with a frame error rate of
    0.6 and 2 tries a 44-segment run loses the segments that failed both and delivers the rest, where it used to
    be dropped whole at the first segment's failure (so losses grew with the run's size, which a speed-up changes:
    TCP sizes its runs by its pacing rate). With the same draws, 44 single packets lose exactly the same places."""
    run = medium(2, 65e6, per=0.6, retry_limit=1, seed=11)
    run.offer(0.0, 0, 1, 44 * 1500, "run", segments=44)
    (delivered,) = run.run_until(5.0)
    lost = delivered.lost_segments
    assert 0 < len(lost) < 44 and list(lost) == sorted(set(lost)) and all(0 <= k < 44 for k in lost)
    assert run.stats.segments_delivered == 44 - len(lost) and run.stats.retry_drops == len(lost)
    single = medium(2, 65e6, per=0.6, retry_limit=1, seed=11)
    for k in range(44):
        single.offer(0.0, 0, 1, 1500, k)
    assert set(range(44)) - {d.frame.item for d in single.run_until(5.0)} == set(lost)
    whole = medium(2, 65e6, per=0.0, seed=11)
    whole.offer(0.0, 0, 1, 44 * 1500, "run", segments=44)
    assert whole.run_until(5.0)[0].lost_segments == ()


def test_a_channel_on_the_802_11_mac_charges_the_mediums_costs_on_both_networks():
    """`mac = "802.11"` (what [network] air = "medium" writes into a run's radio): a link's rate is the medium's
    saturated goodput (about 0.92 of 65 Mbit/s, less of slower rates: the fixed costs weigh more), and a sleep-network
    transfer costs what the delay line charges: a 272-byte gradient about a fifth of a millisecond at 30 Mbit/s,
    over twice its bits over the rate."""
    import dataclasses

    from nac_onboard.radio.channel import PRESETS, ChannelError
    from nac_onboard.radio.medium import saturated_goodput_bps
    from nac_onboard.radio.transfers import PairLinks

    assert 0.9 < saturated_goodput_bps(65e6) / 65e6 < 0.95
    assert saturated_goodput_bps(6.5e6) / 6.5e6 < saturated_goodput_bps(65e6) / 65e6
    radio = dataclasses.replace(PRESETS["wifi-flight"], mac="802.11", shadowing_sigma_db=0.0, rician_k_db=None)
    near = PairLinks(radio).link(0.0, 2.0)
    assert near.phy_bps == 65e6 and near.capacity_bps == pytest.approx(saturated_goodput_bps(65e6), rel=0.01)
    links = PairLinks(radio)
    charged = links.transfer_s(272 * 8, 25e6, 0.0, phy_bps=30e6)
    assert charged == pytest.approx(expected_message_s(T, 272 + 52, 30e6))
    assert charged > 2 * 272 * 8 / 25e6
    assert PairLinks(PRESETS["wifi-flight"]).transfer_s(272 * 8, 25e6, 0.0, phy_bps=30e6) == 272 * 8 / 25e6
    with pytest.raises(ChannelError, match="mac must be one of efficiency, 802.11"):
        dataclasses.replace(radio, mac="ethernet")


@pytest.mark.parametrize("queue_packets, retry_limit, message", [
    (0, 7, "queue_packets must be >= 1, got 0"), (10, -1, "retry_limit must be in 0..255, got -1"),
    (10, 256, "retry_limit must be in 0..255, got 256")])
def test_a_queue_or_retry_limit_out_of_its_range_is_refused_with_the_range(queue_packets, retry_limit, message):
    with pytest.raises(ValueError, match=message):
        Medium(2, MacTiming(), queue_packets, retry_limit)


def test_a_flushed_station_loses_its_queue_and_the_medium_goes_on_from_idle():
    """A station whose radio loses its power: what it had queued is gone (counted by the caller), it contends for
    nothing, and what it is offered after is sent as from a fresh queue."""
    air = Medium(2, MacTiming(), queue_packets=100, seed=3)
    air.set_links(np.array([[0.0, 30e6], [30e6, 0.0]]), np.zeros((2, 2)))
    for _ in range(5):
        air.offer(0.0, 0, 1, 1500)
    assert air.flush(0) == 5 and air.backlog(0) == 0 and air.next_event_s() is None
    assert air.run_until(1.0) == [] and air.stats.delivered == 0
    air.offer(1.0, 0, 1, 1500)
    delivered = air.run_until(1.01)
    assert len(delivered) == 1 and delivered[0].dst == 1 and air.cw[0] == MacTiming().cw_min
