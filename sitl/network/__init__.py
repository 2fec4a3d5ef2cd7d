"""SITL's kernel network: the companions as network namespaces on a shaped bridge (air, netns), the link shaper
that drives it from the simulated positions (shaper), and its pure rules (shaping)."""
