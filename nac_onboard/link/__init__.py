"""The link between vehicles as sockets and processes: `throughput` (iperf3-style probe and server), `iperf3`
(the real iperf3 beside it) and `emulation` (link emulation by sleeping, over nac_onboard.radio's pure models).
"""
