"""Multi-vehicle MAVLink SITL: pure vectorised physics, per-vehicle protocol state, UDP/TCP server."""
