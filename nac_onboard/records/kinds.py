"""The run directory's files and every record kind, each defined once with its fields and units.

Writers pass these objects (`log.write(kinds.TELEMETRY, ...)`), readers compare against them; no other module
spells a file name or a kind (tests/unit/test_records.py walks the sources for that). `docs/records.md` is made
from this module (`python -m nac_onboard.records`).
"""

from __future__ import annotations

from nac_onboard.records.schema import Field, Kind, RunFile, opt, req

AGENT_WRITER = "nac-onboard agent (nac_onboard/agent/)"
COMPUTE_WRITER = "nac-onboard compute, MPI master (nac_onboard/compute/runner.py)"
RUNNER_WRITER = "nac-sitl experiment (sitl/experiment/runner.py)"

# ---- files ------------------------------------------------------------------------------------------------------
AGENT_LOG = RunFile("agent.jsonl", "VEHICLE/agent.jsonl", "vehicle", AGENT_WRITER,
                    "the companion's telemetry and events")
THROUGHPUT_LOG = RunFile("throughput.jsonl", "VEHICLE/throughput.jsonl", "vehicle", AGENT_WRITER + ", probes",
                         "iperf3-shaped probe results (the master's agent probes its workers)")
TLOG = RunFile("mavlink.tlog", "VEHICLE/mavlink.tlog", "vehicle", AGENT_WRITER,
               "MAVLink frames to and from the autopilot, 8-byte big-endian microseconds before each", jsonl=False)
COMPUTE_LOG = RunFile("compute.jsonl", "compute/compute.jsonl", "run", COMPUTE_WRITER,
                      "the MPI job: its start, one record per iteration, its workers' losses, its summary")
RANK_LOG = RunFile("rank-N.jsonl", "compute/rank-N.jsonl", "rank", "nac-onboard compute, worker rank N",
                   "a worker rank's start and stop")
RESULTS = RunFile("results.npz", "compute/results.npz", "run", COMPUTE_WRITER,
                  "the task's arrays (linreg weights; matmul B and A@B with --save-results), the next iteration and "
                  "the task's name, replaced atomically at each checkpoint: what --resume continues from", jsonl=False)
JOB_LOG = RunFile("job.jsonl", "compute/job.jsonl", "run",
                  "the job's supervisor (nac_onboard/compute/supervisor.py: nac-sitl experiment, nac-onboard mpi run "
                  "--keep-going)", "the MPI job's launches, the stops asked of it and its waits for a worker")
MPIEXEC_LOG = RunFile("mpiexec.log", "compute/mpiexec.log", "run", RUNNER_WRITER, "mpiexec's own output",
                      jsonl=False)
START_FILE = RunFile("start", "compute/start", "run", RUNNER_WRITER,
                     "the go: the simulated time the job ends at, written when the missions start", jsonl=False)
NETWORK_LOG = RunFile("network.jsonl", "network.jsonl", "run", "the link shaper (sitl/network/shaper.py)",
                      "the kernel network's link rates over time")
EXPERIMENT_LOG = RunFile("experiment.json", "experiment.json", "run", RUNNER_WRITER,
                         "the experiment: its settings, its faults as they happen, how it ended (JSON Lines)")
ENERGY_LOG = RunFile("energy.jsonl", "energy.jsonl", "run", RUNNER_WRITER,
                     "each vehicle's power (flight, compute, radio) and both its packs, once a simulated second")
CLOCK_FILE = RunFile("clock.json", "clock.json", "run", RUNNER_WRITER,
                     "the run's one clock: simulated seconds and pace, read by every process ($NAC_SIM_CLOCK)",
                     jsonl=False)
CHANNEL_FILE = RunFile("channel.toml", "config/channel.toml", "run", RUNNER_WRITER,
                       "the run's radio, overrides applied: every process of the run loads it", jsonl=False)
REPLAY_TABLE = RunFile("replay.json", "config/replay.json", "run", RUNNER_WRITER,
                       "a recorded run's link rates, for the sleep network's processes", jsonl=False)
AGENT_CONFIG = RunFile("VEHICLE.toml", "config/VEHICLE.toml", "vehicle", RUNNER_WRITER, "each agent's config",
                       jsonl=False)
FLEET_KEY = RunFile("fleet.key", "config/fleet.key", "run", RUNNER_WRITER,
                    "the fleet's peer-state signing key, fresh per run (mode 0600)", jsonl=False)
PEER_FRESHNESS = RunFile("peer-freshness-VEHICLE.json", "config/peer-freshness-VEHICLE.json", "vehicle",
                         AGENT_WRITER, "the last sequence the agent accepted from each peer (peers.state_file; on a "
                         "companion $STATE_DIRECTORY or log.dir)", jsonl=False)
HOSTFILE = RunFile("hostfile", "config/hostfile", "run", RUNNER_WRITER, "MPICH's hostfile", jsonl=False)
REPORT = RunFile("report.md", "report.md", "run", "nac-ground logs analyze (ground/logs/report.py)",
                 "the analysis report", jsonl=False)
SUMMARY = RunFile("summary.json", "analysis/summary.json", "run", "nac-ground logs analyze",
                  "the report's summary figures", jsonl=False)
VIEW_PNG = RunFile("view.png", "view.png", "run", RUNNER_WRITER + " with --view", "the web view's screenshot",
                   jsonl=False)

CONFIG_DIR = "config"
COMPUTE_DIR = "compute"
ANALYSIS_DIR = "analysis"
#: VEHICLE/iperf3-PEER[.anything].json: the output of `iperf3 --client PEER --json` run on VEHICLE, read as probes
IPERF3_GLOB = "iperf3-*.json"

FILES = (AGENT_LOG, THROUGHPUT_LOG, TLOG, COMPUTE_LOG, RANK_LOG, RESULTS, JOB_LOG, MPIEXEC_LOG, START_FILE, NETWORK_LOG,
         EXPERIMENT_LOG, ENERGY_LOG, CLOCK_FILE, CHANNEL_FILE, REPLAY_TABLE, AGENT_CONFIG, FLEET_KEY, PEER_FRESHNESS,
         HOSTFILE, REPORT, SUMMARY, VIEW_PNG)


# ---- kinds in every JSON Lines file --------------------------------------------------------------------------
ANY_FILE = RunFile("*.jsonl", "any JSON Lines file above", "run", "every writer (nac_onboard/flight_log.py)",
                   "records every log writes")
SCHEMA = Kind("schema", ANY_FILE, "the first record of every file: which schema its records follow", (
    req("schema_version", "integer", "", "nac_onboard.records.SCHEMA_VERSION of the writer"),
    req("file", "string", "", "the file's name"),
))
LOG_GAP = Kind("log_gap", ANY_FILE, "records lost to a full disk, written when writing works again", (
    req("since_s", "number", "s", "unix time of the first lost record"),
    req("records_lost", "integer", "", "records not written"),
    req("bytes_lost", "integer", "bytes", "their size"),
    req("error", "string", "", "why, e.g. ENOSPC"),
))

# ---- the agent: VEHICLE/agent.jsonl --------------------------------------------------------------------------
_CHANGE = (req("value", "any", "", "the new value"), req("previous", "any", "", "the value before (null at first)"))
AGENT_STARTED = Kind("agent_started", AGENT_LOG, "the agent started", (
    req("vehicle", "string", "", "vehicle id"), req("role", "string", "", "master or worker"),
    req("config", "string", "", "config file"), req("autopilot", "string", "", "autopilot URI"),
    req("run_dir", "string", "", "where it logs"), req("pid", "integer", "", "process id"),
    opt("host", "string", "", "the companion's hostname (runs from several companions are merged on the ground)"),
    req("mpi_build", "any", "", "the MPI build found on this companion"),
    opt("tlog_clock", "string", "", "the .tlog's stamps: wall, or simulated (a sped-up SITL run: unix time at "
                                    "simulated 0 plus simulated seconds, so tools read durations in simulated time)"),
    opt("tlog_anchor_s", "number", "s", "simulated .tlog: the unix time its simulated 0 stands for"),
))
AGENT_READY = Kind("agent_ready", AGENT_LOG, "sockets open, probes scheduled", (
    req("peers_listen", "string", "", "HOST:PORT of peer state"), req("state_feed", "string", "", "HOST:PORT"),
    opt("throughput_port", "integer", "", "the throughput server's port"),
    req("probing", "boolean", "", "whether this agent probes its peers"),
    opt("probe_duty_cycle", "number", "", "share of time spent probing"),
))
AGENT_STOPPED = Kind("agent_stopped", AGENT_LOG, "the agent stopped, with its counters", (
    req("reason", "string", "", "why"), req("peer_rejects", "object", "", "peer messages refused, by reason"),
    opt("stop_requested_s", "number", "s", "unix time the stop signal came (null: closed without one); the logs "
                                           "end about there, the record after the agent's cleanup"),
    *(req(name, "integer", "", doc) for name, doc in (
        ("frames_in", "MAVLink frames from the autopilot"), ("frames_out", "frames sent to the autopilot"),
        ("frames_routed", "frames relayed between endpoints"), ("telemetry", "telemetry records"),
        ("peer_msgs", "peer states taken"), ("bad_peer_msgs", "peer datagrams refused"),
        ("feed_requests", "state-feed answers"), ("bad_feed_requests", "state-feed requests refused"),
        ("routing_refused", "frames refused by routing.allow"))),
    opt("autopilot_refused", "integer", "", "datagrams or connections refused on the autopilot link (not its peer)"),
))
WARNING = Kind("warning", AGENT_LOG, "a setting that lowers safety", (req("text", "string", "", "what and why"),))
ROUTING_ERROR = Kind("routing_error", AGENT_LOG, "a routing endpoint could not open", (
    req("endpoint", "string", "", "URI"), req("error", "string", "", "why")))
ROUTING_REFUSED = Kind("routing_refused", AGENT_LOG, "frames refused from senders not in routing.allow (rate-limited)",
                       (req("frames_since_last_record", "integer", "", "refused since the last such record"),
                        req("senders", "list", "", "HOST:PORT of the refused senders")))
TELEMETRY = Kind("telemetry", AGENT_LOG, "the autopilot's position and state, at log.telemetry_hz", (
    req("sysid", "integer", "", "MAVLink system id"), req("time_boot_ms", "integer", "ms", "autopilot's boot clock"),
    req("lat_deg", "number", "deg", "WGS-84 latitude"), req("lon_deg", "number", "deg", "WGS-84 longitude"),
    req("alt_m", "number", "m", "altitude above mean sea level"), req("rel_alt_m", "number", "m", "above home"),
    req("vel_ned_mps", "list", "m/s", "velocity north, east, down"),
    req("roll_deg", "number", "deg", "roll"), req("pitch_deg", "number", "deg", "pitch"),
    req("yaw_deg", "number", "deg", "yaw"), opt("battery_pct", "number", "%", "battery remaining"),
    opt("voltage_v", "number", "V", "battery voltage"), req("mode", "string", "", "flight mode"),
    req("armed", "boolean", "", "armed"), opt("landed", "string", "", "landed state"),
    opt("mission_seq", "integer", "", "current mission item"), opt("mission_total", "integer", "", "mission items"),
))
MODE = Kind("mode", AGENT_LOG, "the flight mode changed", _CHANGE)
ARMED = Kind("armed", AGENT_LOG, "armed or disarmed", _CHANGE)
LANDED_STATE = Kind("landed_state", AGENT_LOG, "EXTENDED_SYS_STATE's landed state changed", _CHANGE)
MISSION_CURRENT = Kind("mission_current", AGENT_LOG, "the current mission item changed",
                       (*_CHANGE, opt("total", "integer", "", "mission items")))
MISSION_STATE = Kind("mission_state", AGENT_LOG, "MISSION_CURRENT's mission state changed", _CHANGE)
MISSION_ITEM_REACHED = Kind("mission_item_reached", AGENT_LOG, "MISSION_ITEM_REACHED",
                            (req("seq", "integer", "", "the item"),))
STATUSTEXT = Kind("statustext", AGENT_LOG, "the autopilot's STATUSTEXT (rate-limited: the same text at most once "
                  "per 5 s, at most 10 records a second)", (
    req("severity", "integer", "", "MAV_SEVERITY"), req("text", "string", "", "the text"),
    opt("repeated", "integer", "", "times the previous record's text came again, not logged, since that record"),
    opt("dropped_since_last", "integer", "", "other texts not logged since the previous record (over the rate)"),
    opt("counts_only", "boolean", "", "written at the agent's stop to carry the counts: its text is the previous "
                                      "record's, not heard again")))
LINK_OPEN_FAILED = Kind("link_open_failed", AGENT_LOG, "the autopilot link could not open (retried)", (
    req("uri", "string", "", "autopilot URI"), req("error", "string", "", "why"),
    req("attempts", "integer", "", "failed attempts so far")))
LINK_OPENED = Kind("link_opened", AGENT_LOG, "the autopilot link opened", (
    req("uri", "string", "", "autopilot URI"), req("after_attempts", "integer", "", "attempts it took")))
LINK_ERROR = Kind("link_error", AGENT_LOG, "the autopilot link failed", (
    req("uri", "string", "", "autopilot URI"), req("error", "string", "", "why")))
AUTOPILOT_PEER = Kind("autopilot_peer", AGENT_LOG, "a listening autopilot link took its one peer (autopilot.peer)", (
    req("uri", "string", "", "autopilot URI"), req("peer", "string", "", "HOST:PORT taken as the autopilot"),
    req("configured", "string", "", "autopilot.peer as set (\"\" = the first sender that speaks MAVLink)")))
AUTOPILOT_REFUSED = Kind("autopilot_refused", AGENT_LOG,
                         "datagrams or connections refused on the autopilot link from others than its peer "
                         "(rate-limited)", (
                             req("refused_since_last_record", "integer", "", "refused since the last such record"),
                             req("last_sender", "string", "", "HOST:PORT of the last refused sender"),
                             req("peer", "string", "", "HOST:PORT of the autopilot (\"\" before it spoke)")))
LINK_UP = Kind("link_up", AGENT_LOG, "the autopilot's first heartbeat", (
    req("sysid", "integer", "", "its system id"), req("autopilot", "integer", "", "MAV_AUTOPILOT"),
    req("vehicle_type", "integer", "", "MAV_TYPE"), req("mavlink_version", "integer", "", "from HEARTBEAT")))
LINK_LOST = Kind("link_lost", AGENT_LOG, "the autopilot went silent or its link failed", (
    req("sysid", "integer", "", "its system id"), req("why", "string", "", "silent or error"),
    opt("silent_s", "number", "s", "silence that declared it lost")))
LINK_RESTORED = Kind("link_restored", AGENT_LOG, "the autopilot is heard again", (
    req("sysid", "integer", "", "its system id"), req("outage_s", "number", "s", "how long it was lost")))
_PEER = (req("peer", "string", "", "peer vehicle id"), req("role", "string", "", "its role"),
         req("host", "string", "", "its address"))
PEER_SEEN = Kind("peer_seen", AGENT_LOG, "a peer heard for the first time or again",
                 (*_PEER, opt("probe_port", "integer", "", "its throughput server port")))
PEER_LOST = Kind("peer_lost", AGENT_LOG, "a peer went silent", (*_PEER, req("silent_s", "number", "s", "silence")))
PEER_REJECTED = Kind("peer_rejected", AGENT_LOG, "peer datagrams refused (rate-limited)", (
    req("last_sender", "string", "", "address of the last refused sender"),
    req("last_reason", "string", "", "why it was refused"),
    req("since_last_record", "object", "", "refusals since the last such record, by reason")))
THROUGHPUT_SERVER_RESTARTED = Kind("throughput_server_restarted", AGENT_LOG, "the throughput server died and was "
                                   "started again", (req("port", "integer", "", "its port"),
                                                     req("refused_before", "integer", "", "connections it refused")))
THROUGHPUT_SERVER_FAILED = Kind("throughput_server_failed", AGENT_LOG, "the throughput server could not restart", (
    req("port", "integer", "", "its port"), req("error", "string", "", "why")))

# ---- the agent's probes: VEHICLE/throughput.jsonl ----------------------------------------------------------------
_PROBE = (req("client", "string", "", "probing vehicle"), req("server", "string", "", "probed vehicle"),
          req("host", "string", "", "server address"), req("port", "integer", "", "server port"),
          req("t_sim_s", "number", "s", "simulated time at the start (the run's clock)"),
          req("speedup", "number", "", "simulated seconds per wall second"))
THROUGHPUT = Kind("throughput", THROUGHPUT_LOG, "one probe, shaped as iperf3 --json (start, intervals, end)", (
    *_PROBE,
    opt("start", "object", "", "iperf3's start: timestamp.timesecs, connected, test_start"),
    opt("intervals", "list", "", "iperf3's intervals, each streams[] and sum"),
    opt("end", "object", "", "iperf3's end: sum_sent, sum_received (bits_per_second in bit/s, bytes, seconds)"),
    opt("server_output_json", "object", "", "the server's own intervals"),
    opt("error", "string", "", "why the probe failed"),
    opt("error_kind", "string", "", "link (nothing got through) or server (the server's answer was wrong)"),
    opt("emulated_channel", "string", "", "sleep network: the channel model"),
    opt("emulated_rate_bps", "number", "bit/s", "sleep network: the model's rate"),
    opt("duration_wall_s", "integer", "s", "real iperf3: its whole-second test length"),
    req("positions", "object", "", "the pair's positions at the start and the end"),
    opt("distance_m", "number", "m", "distance at the start"), opt("distance_end_m", "number", "m", "at the end"),
), open="real iperf3's own JSON keys, kept as it wrote them")
PROBE_SKIPPED = Kind("probe_skipped", THROUGHPUT_LOG, "no measurement: a position of the pair is not known yet, "
                     "or the agent stopped during the probe",
                     (*_PROBE, req("reason", "string", "", "why")))
PROBE_FAILED = Kind("probe_failed", THROUGHPUT_LOG, "the probe could not be made (an error in the agent, not a "
                    "measurement: left out of the analysis); the schedule goes on", (
    req("server", "string", "", "the vehicle to be probed"), req("host", "string", "", "its address"),
    req("port", "integer", "", "its port (as given, even out of range)"), req("error", "string", "", "what failed")))

# ---- the MPI job: compute/compute.jsonl, compute/rank-N.jsonl ------------------------------------------------
RUN_STARTED = Kind("run_started", COMPUTE_LOG, "the job is set up (after one untimed warm-up exchange)", (
    req("warmup_s", "number", "s", "the warm-up exchange"), req("task", "string", "", "linreg or matmul"),
    req("workers", "integer", "", "worker ranks"), req("shards", "list", "", "each worker's rows [start, end)"),
    req("emulate", "string", "", "link emulation: none, positions, script"),
    req("pad_bits", "integer", "bit", "padding added to each message"),
    req("speedup", "number", "", "simulated seconds per wall second"),
    opt("channel", "string", "", "the emulated channel"), opt("channel_validity", "any", "", "its model's range"),
    opt("iterations", "integer", "", "iterations asked for"), opt("duration_s", "number", "s", "duration asked for"),
    req("timeout_s", "number", "s", "a worker's answer deadline"), req("on_missing", "string", "", "skip or reassign"),
    req("allocation", "string", "", "rows per worker: equal, capacity, speed or energy"),
    req("pid", "integer", "", "master's pid"),
    opt("device", "string", "", "the companions' device profile (host: this machine's speed)"),
    opt("cpu_slowdown", "number", "", "the profile's CPU seconds per CPU second of this host"),
    opt("device_source", "string", "", "who measured the slowdown, on what"),
    opt("worker_devices", "list", "", "each worker's device profile, rank order (--device-of: one unlike the rest)"),
    opt("replan_every", "integer", "", "blocks re-planned every this many iterations and on absences (0: never)"),
    opt("link_rates", "string", "", "what the allocation expects of the links: model or probes"),
))
RESUMED = Kind("resumed", COMPUTE_LOG, "a restarted master continued from its checkpoint (--resume)", (
    req("iteration", "integer", "", "the first iteration it runs: the checkpoint's"),
    req("checkpoint", "string", "", "the checkpoint's path")))
STARTED = Kind("started", COMPUTE_LOG, "the go arrived (--start-file)", (
    req("start_file", "string", "", "its path"), opt("end_at_s", "number", "s", "simulated time to end at")))
ITERATION = Kind("iteration", COMPUTE_LOG, "one iteration; `workers` holds one list per field, one entry per worker", (
    req("iteration", "integer", "", "from 0"), req("start_s", "number", "s", "unix time the inputs went out"),
    req("end_s", "number", "s", "unix time it was combined"), req("duration_s", "number", "s", "wall time"),
    opt("start_sim_s", "number", "s", "simulated start (absent: the analysis uses start_s)"),
    opt("duration_sim_s", "number", "s", "simulated time (absent: the analysis uses duration_s)"),
    req("workers", "object", "", "rank, vehicle, present, distance_m (m), rate_bps (bit/s), loss, absent (why: "
                                 "out_of_range, no_position, timeout, unresponsive, agent_lost: its agent unheard "
                                 "by the master's, or heard restarted), "
                                 "bytes_down, bytes_up (bytes), down_s, up_s, "
                                 "compute_s (s)"),
    req("complete", "boolean", "", "every worker's block arrived"),
    opt("master_compute_s", "number", "s", "with a device profile: the master's own work (input and combine) on the "
                                           "device's clock"),
    opt("master_queue_s", "number", "s", "sleep emulation with --probe-backlog-packets: how long the inputs waited "
                                         "behind the probes' packets in the master's transmit queue (simulated)"),
    opt("cost", "number", "", "linreg: training cost (mean squared error / 2) before the update"),
    opt("rows_used", "integer", "", "linreg: data rows whose gradients arrived"),
    opt("reassigned", "object", "", "a task's plan for missing blocks (matmul --on-missing reassign): who computed "
                                    "whose rows"),
), open="a task's own fields (cost and rows_used are linreg's; the coded tasks' decoded_from, decode_s, condition "
        "and decode_error, and matmul_bpcc's units, in their modules' docstrings): a new task in "
        "nac_onboard/compute/tasks/ adds its fields from its own module")
RUN_SUMMARY = Kind("run_summary", COMPUTE_LOG, "the job's end", (
    req("task", "string", "", "the task's name (linreg, matmul, or a coded one: linreg_gc, matmul_mds, matmul_bpcc)"),
    req("iterations", "integer", "", "iterations run"),
    req("complete_iterations", "integer", "", "with every worker"),
    req("ended_by", "string", "", "why it stopped: iterations, duration, end_at, or stopped (SIGTERM: its "
                                  "supervisor restarting it, or its launcher gone)"),
    req("elapsed_s", "number", "s", "wall time"), req("elapsed_sim_s", "number", "s", "simulated time"),
    req("mean_duration_s", "number", "s", "mean iteration time"), req("p95_duration_s", "number", "s", "95th pct"),
    req("absent_iterations", "object", "", "iterations each rank missed"),
    req("stale_results", "integer", "", "late answers dropped"),
    req("lost_workers", "list", "", "ranks unresponsive, or whose agents were lost, at the end"),
    req("failed_workers", "list", "", "ranks whose MPI calls failed"),
    opt("late_cpu_segments", "integer", "", "work segments (all ranks) this host did more slowly than the device "
                                            "profile on the run's clock: their timings depend on the speed-up"),
    opt("late_cpu_s_worst_rank", "number", "s", "simulated: by how much, in all, the late work segments of the rank "
        "with the most overran the device's time"),
    opt("final_cost", "number", "", "linreg: the last cost"),
), open="a task's own fields (Task.final(); final_cost is linreg's)")
BLOCKS_PLANNED = Kind("blocks_planned", COMPUTE_LOG, "the master re-planned the workers' blocks (--replan-every)", (
    req("iteration", "integer", "", "the first iteration on the new blocks"),
    req("why", "string", "", "period (every --replan-every iterations), absent or back (a worker left or rejoined)"),
    req("shares", "list", "", "each worker's share, rank order (0: planned out)"),
    req("bounds", "list", "", "each worker's [start, stop) of the task's rows (or coded units), rank order"),
    req("planned_out", "list", "", "ranks absent or unresponsive, given nothing"),
    opt("rates_bps", "list", "bit/s", "what the allocation expected of each worker's link (capacity, speed)"),
    opt("link_rates", "string", "", "where those rates came from: model, or probes (the model where none fresh)")))
WORKER_LOST = Kind("worker_lost", COMPUTE_LOG, "an MPI call to a worker failed: it is not sent to again", (
    req("rank", "integer", "", "MPI rank"), req("vehicle", "string", "", "its vehicle"),
    req("error", "string", "", "MPI's error")))
WORKER_REFUSED = Kind("worker_refused", COMPUTE_LOG, "a worker would compute another problem than the master's "
                                                    "(another data set, task or size): it ended itself (exit 2), "
                                                    "the job goes on without it", (
    req("rank", "integer", "", "MPI rank"), req("vehicle", "string", "", "its vehicle"),
    req("why", "string", "", "its problem and the master's, in words")))
WORKER_UNRESPONSIVE = Kind("worker_unresponsive", COMPUTE_LOG, "a worker missed several iterations in a row", (
    req("rank", "integer", "", "MPI rank"), req("vehicle", "string", "", "its vehicle"),
    req("iteration", "integer", "", "when"), req("missed", "integer", "", "iterations missed in a row")))
WORKER_BACK = Kind("worker_back", COMPUTE_LOG, "an unresponsive worker answered again", (
    req("rank", "integer", "", "MPI rank"), req("vehicle", "string", "", "its vehicle")))
CHECKPOINT_FAILED = Kind("checkpoint_failed", COMPUTE_LOG, "a checkpoint could not be written (a full disk): its "
                         "partial file removed, the previous one kept, training goes on, the next one tries again", (
    req("iteration", "integer", "", "the iteration it was for"),
    req("error", "string", "", "why, e.g. ENOSPC: No space left on device"),
    req("kept_iteration", "any", "", "the iteration of the checkpoint kept (null: none yet)")))
WORKER_STARTED = Kind("worker_started", RANK_LOG, "a worker rank started", (
    req("rank", "integer", "", "MPI rank"), req("pid", "integer", "", "process id"),
    req("host", "string", "", "MPI processor name")))
BLOCK_TAKEN = Kind("block_taken", RANK_LOG, "a worker took its block of the data, at the start and at each re-plan",
                   (req("rank", "integer", "", "MPI rank"),
                    req("block", "list", "", "its [start, stop) of the task's rows (matmul_bpcc: coded units)"),
                    req("take_s", "number", "s", "wall time to split and take it: for a coded task, its encoding")))
WORKER_STOPPED = Kind("worker_stopped", RANK_LOG, "a worker rank stopped", (
    req("rank", "integer", "", "MPI rank"), req("finalizes", "boolean", "", "whether it called MPI_Finalize")))
WORKER_GAVE_UP = Kind("worker_gave_up", RANK_LOG, "a worker heard nothing from the master for its idle timeout and "
                      "ends (exit 3; each worker by its own timeout): recorded first, as hydra can end the job "
                      "before a rank's stderr is forwarded", (
    req("rank", "integer", "", "MPI rank"), req("idle_timeout_s", "number", "s", "the wait it gave the master")))

# ---- the job's supervisor: compute/job.jsonl --------------------------------------------------------------------
JOB_LAUNCHED = Kind("job_launched", JOB_LOG, "mpiexec started for the job: the first time, or again", (
    req("launch", "integer", "", "1 for the first, then 2, 3..."),
    req("why", "string", "", "start; rejoin (a worker came back); launcher lost (mpiexec died under the master: a "
                             "companion's proxy connection closed); stopped; ended without its summary"),
    req("workers", "list", "", "the vehicles of its workers, rank order"),
    req("resume", "boolean", "", "whether it continues from the checkpoint (--resume)"),
    req("from_iteration", "any", "", "the checkpoint's iteration (null: a fresh start)"),
    req("pid", "integer", "", "mpiexec's process id"), req("t_sim_s", "number", "s", "on the run's clock")))
JOB_STOPPING = Kind("job_stopping", JOB_LOG, "the supervisor asked the master to stop (SIGTERM) so that the job "
                                             "starts again with a worker that came back", (
    req("launch", "integer", "", "the launch asked"), req("why", "string", "", "rejoin"),
    req("vehicles", "list", "", "the workers it starts again for"), req("t_sim_s", "number", "s", "the run's clock")))
JOB_WAITING = Kind("job_waiting", JOB_LOG, "the job waits before it starts again (longer each time in a row)", (
    req("why", "string", "", "no worker heard, or the last start was not set up"),
    req("retry_in_s", "number", "s", "simulated"), req("t_sim_s", "number", "s", "the run's clock")))
JOB_ENDED = Kind("job_ended", JOB_LOG, "an mpiexec of the job ended", (
    req("launch", "integer", "", "which"), req("exit_code", "any", "", "mpiexec's"),
    req("ended_by", "any", "", "its master's run_summary.ended_by (null: no summary: the master died)"),
    req("t_sim_s", "number", "s", "the run's clock")))

# ---- the kernel network: network.jsonl ---------------------------------------------------------------------------
LINK_RATES = Kind("link_rates", NETWORK_LOG, "every pair's link, one list per field, one entry per pair", (
    req("t_sim_s", "number", "s", "simulated time"), req("speedup", "number", "", "the pace applied"),
    req("a", "list", "", "first vehicle of each pair"), req("b", "list", "", "second vehicle"),
    req("distance_m", "list", "m", "distance"), req("rate_bps", "list", "bit/s", "rate applied"),
    req("loss", "list", "", "packet loss applied (0-1)"), req("snr_db", "list", "dB", "signal to noise"),
    req("mcs", "list", "", "802.11n MCS index (-1 out of range)"),
    opt("budget_bps", "number", "bit/s", "the access point's shared airtime"),
    req("source", "string", "", "the channel model, or replay:FILE"),
))
SHAPER_LATE = Kind("shaper_late", NETWORK_LOG, "the shaper fell behind its period (rate-limited)", (
    req("behind_s", "number", "s", "how far behind"), req("late_updates", "integer", "", "late so far"),
    req("note", "string", "", "what it means")))
SHAPER_FAILED = Kind("shaper_failed", NETWORK_LOG, "tc or nft failed: links keep their last rates",
                     (req("error", "string", "", "why"),))
AIR_MEDIUM = Kind("air_medium", NETWORK_LOG, "the frame-level air's counters (delay line), once a wall second", (
    req("t_sim_s", "number", "s", "simulated time"), req("offered", "integer", "", "packets queued so far"),
    req("delivered", "integer", "", "packets delivered so far"),
    opt("segments_delivered", "integer", "", "the same, a segmentation offload's run counted as its packets"),
    req("queue_drops", "integer", "", "packets dropped at a full transmit queue"),
    req("retry_drops", "integer", "", "packets lost after every MAC retry (a run's segments each count)"),
    opt("runs_cut", "integer", "", "offload runs delivered in part: their other segments as packets of their own"),
    req("exchanges", "integer", "", "channel accesses"), req("collisions", "integer", "", "of them, collisions"),
    req("busy_s", "number", "s", "air time used (simulated)"),
    req("backlog", "list", "", "each station's queue now, in packets"),
    opt("queue_p50_s", "number", "s", "median wait from queue to air since the last record (simulated)"),
    opt("queue_p50_by_station_s", "list", "s", "the same per sending station, in backlog's order (null: sent nothing)"),
    opt("stations", "list", "", "the vehicle of each station, in backlog's order"),
    opt("air_p50_s", "number", "s", "median time on the air, tries included, since the last record"),
    req("late", "integer", "", "deliveries written over 1 ms (simulated) after their time: the host fell behind"),
    req("max_late_s", "number", "s", "the latest of them"),
    opt("late_p50_s", "number", "s", "median time a delivery was written after its time since the last record "
        "(simulated): the host's own work on a frame beyond what its hold leaves"),
    opt("lead_s", "number", "s", "wall: how early each delivery is written, the host's own pass (measured at start)"),
    opt("packets_in", "integer", "", "packets read from the stations' air0 so far (an offload run counted once)"),
    opt("passed", "integer", "", "of them, passed straight through while the lead was timed (before the medium)"),
    opt("not_ipv4", "integer", "", "of them, not IPv4: not carried (IPv6 is off on air0)"),
    opt("unknown_destination", "integer", "", "of them, to an address no station has: not carried"),
    opt("write_failed", "integer", "", "packets delivered that the receiver's air0 refused (down, or its queue "
        "full): lost on this host, not by the medium"),
    opt("updates", "integer", "", "link updates taken"), opt("bad_updates", "integer", "", "link updates refused"),
    opt("cpus_held_awake", "boolean", "", "whether the delay line holds the CPUs' wake-up latency at 0"),
    opt("cpu_s", "number", "s", "the delay line's own CPU time so far (this host's)"),
    opt("wall_s", "number", "s", "wall time since the delay line started: with cpu_s, its share of a core"),
    opt("flushed", "integer", "", "packets queued at a station when its radio went off (a lost companion): gone "
        "with it"),
    opt("stations_off", "list", "", "the stations whose radio is off now, by index in backlog's order: nothing "
        "reaches them, frames to them are tried to the retry limit and lost"),
))

# ---- the experiment: experiment.json ---------------------------------------------------------------------------
EXPERIMENT = Kind("experiment", EXPERIMENT_LOG, "the experiment's settings, at its start", (
    req("scenario", "string", "", "scenario name"), req("path", "string", "", "scenario file"),
    req("speedup", "number", "", "simulated seconds per wall second"), req("speedup_note", "string", "", "in words"),
    req("duration_s", "number", "s", "simulated duration"),
    req("network", "object", "", "mode (kernel or sleep), why, sharing, period_s"),
    req("radio", "object", "", "name, describe, sources"), req("links", "string", "", "model or replay:FILE"),
    opt("probes", "object", "",
        "the scenario's [throughput]: period_s, duration_s, interval_s, tool, concurrent (null: none)"),
    req("vehicles", "list", "", "each {id, role}"),
    req("missions", "object", "", "vehicle -> [[lat_deg, lon_deg], ...] of its mission"),
))
FAULT = Kind("fault", EXPERIMENT_LOG, "a scheduled fault switched on or off, as it happens", (
    req("vehicle", "string", "", "vehicle id"), req("fault", "string", "", "fault kind"),
    req("state", "string", "", "on or off"), req("t_sim_s", "number", "s", "simulated time since the missions")))
EXPERIMENT_ENDED = Kind("experiment_ended", EXPERIMENT_LOG, "how the experiment ended", (
    req("outcome", "string", "", "completed, interrupted, ..."), req("detail", "string", "", "in words"),
    req("faults", "list", "", "every fault event: t_sim_s, vehicle, kind, state")))

# ---- energy: energy.jsonl -----------------------------------------------------------------------------------------
ENERGY = Kind("energy", ENERGY_LOG, "a vehicle's mean power over the last simulated interval, its packs after it", (
    req("t_sim_s", "number", "s", "simulated time since the missions, at the interval's end"),
    req("dt_s", "number", "s", "the interval (simulated)"), req("vehicle", "string", "", "vehicle id"),
    req("flight_w", "number", "W", "the flight pack's output: propulsion and avionics"),
    req("compute_w", "number", "W", "the companion computer's draw"),
    req("radio_w", "number", "W", "the Wi-Fi radio's draw"),
    req("companion_w", "number", "W", "the companion pack's output: (compute + radio) / the converters' efficiency"),
    req("busy_share", "number", "", "the rank's share of the interval computing (0-1)"),
    req("tx_share", "number", "", "the station's share of the interval sending"),
    req("rx_share", "number", "", "the station's share of the interval receiving"),
    opt("air_rate_bps", "number", "bit/s", "the rate its bytes took the air at: its link's, else the radio's PHY"),
    req("flight_soc", "number", "", "flight pack state of charge (0-1)"),
    req("flight_v", "number", "V", "flight pack voltage"),
    req("companion_soc", "number", "", "companion pack state of charge (0-1)"),
    req("companion_v", "number", "V", "companion pack voltage (0: empty)")))
BATTERY_EMPTY = Kind("battery_empty", ENERGY_LOG, "a companion pack ran out: its computer, rank and radio stop", (
    req("t_sim_s", "number", "s", "simulated time since the missions"), req("vehicle", "string", "", "vehicle id"),
    req("pack", "string", "", "companion"), req("stopped", "list", "", "what stopped: agent, rank, radio")))
ENERGY_PLAN = Kind("energy_plan", ENERGY_LOG, "the energy models of the run, at its start", (
    req("frames", "object", "", "vehicle -> NAC_FRAME's frame name"),
    req("companion", "object", "", "name, idle_w, busy_w, source"),
    req("radio", "object", "", "name, idle_w, tx_w, rx_w, phy_rate_bps, source"),
    req("companion_packs", "object", "", "vehicle -> [cells, capacity mAh]"),
    req("dc_dc_efficiency", "number", "", "the companion's converters"),
    req("radio_counted", "boolean", "", "station bytes counted (kernel network); false: the radio idles")))

KINDS: tuple[Kind, ...] = tuple(v for v in dict(globals()).values() if isinstance(v, Kind))
BY_NAME: dict[str, Kind] = {k.name: k for k in KINDS}
#: the agent's state changes, by what changed
CHANGES = {"mode": MODE, "armed": ARMED, "landed": LANDED_STATE, "mission_seq": MISSION_CURRENT,
           "mission_state": MISSION_STATE}
assert len(BY_NAME) == len(KINDS), "two kinds share a name"
__all__ = ["Field", "Kind", "RunFile", "KINDS", "BY_NAME", "FILES"]
