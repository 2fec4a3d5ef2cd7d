"""Loopback ports handed out to local SITLs, agents and benchmarks (sitl/launcher.py)."""

import random

from sitl import launcher


def test_a_port_handed_out_in_a_block_is_never_handed_out_again(monkeypatch):
    """A SITL's block is free when handed out and bound later (an agent binds its companion port when it starts):
    free_port must not give that port to anyone else meanwhile, even when it draws it first."""
    base = launcher.allocate_base_port(2, slots=2)
    companion = base + 10 + 1  # the second vehicle's companion port, bound by its agent only later
    draws = iter([companion, companion])
    real = random.randrange
    monkeypatch.setattr(launcher.random, "randrange", lambda *args: next(draws, None) or real(*args))
    port = launcher.free_port()
    assert port != companion
    assert launcher.free_port() != port
