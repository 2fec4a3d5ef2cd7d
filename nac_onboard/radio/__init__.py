"""The radio between vehicles, pure (numpy, no sockets, clocks or sleeping; DESIGN.md 6):

  air_link    the formulas (path loss, shadowing, fading, 802.11n rates and losses) and the time-varying state
              of pairs of vehicles, stepped by the caller
  channel     a radio as data: ChannelModel's fields, its median behaviour at a distance, presets with sources
  replay      a recorded flight's per-pair throughput, in place of the model where it has the pair
  transfers   each pair's link now and how long a transfer takes on it (what the sleep emulation sleeps)
  files       the package's one edge: channel TOML files (and presets by name), replay tables (JSON)

What uses it over sockets and processes lives elsewhere: nac_onboard.link (throughput probe and server, iperf3,
emulation by sleeping), sitl.network (the kernel network's shaper), the experiment runner.
"""
