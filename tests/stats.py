"""Bounds that come from the sample a test has (ground.logs.agreement): a measured quantity is judged only as far as
its sample allows."""

from ground.logs.agreement import MIN_SAMPLES, agrees_within, median_interval

__all__ = ["MIN_SAMPLES", "agrees_within", "median_interval"]
