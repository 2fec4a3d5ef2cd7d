import pytest

from sitl.server import Sitl, SitlConfig
from tests.integration.gcs import Gcs


@pytest.fixture
def start_sitl(base_port):
    """Factory: an in-process SITL on its own ports, stopped when the test ends."""
    started: list[Sitl] = []

    def start(vehicles: int = 1, speedup: float = 20.0, config: SitlConfig | None = None, **kwargs) -> Sitl:
        """A new SITL; with config, one on the same ports as an earlier one (a restarted autopilot)."""
        if config is None:
            base = base_port(vehicles)
            config = SitlConfig(vehicles=vehicles, speedup=speedup, gcs_base_port=base,
                                companion_base_port=base + 1, tcp_base_port=kwargs.pop("tcp_base_port", 0),
                                **kwargs)
        sim = Sitl(config).start()
        started.append(sim)
        return sim

    yield start
    for sim in started:
        sim.stop()


@pytest.fixture
def gcs_for():
    """Factory: a pymavlink ground station listening on a vehicle's ground port, closed at the end."""
    opened: list[Gcs] = []

    def connect(sim, vehicle: int = 0, companion: bool = False) -> Gcs:
        c = sim.config
        port = (c.companion_base_port if companion else c.gcs_base_port) + c.port_step * vehicle
        gcs = Gcs(port, sysid=vehicle + 1)
        opened.append(gcs)
        gcs.wait_heartbeat()
        return gcs

    yield connect
    for gcs in opened:
        gcs.close()


@pytest.fixture
def start_agent(tmp_path):
    """Factory: `nac-onboard agent` child processes from config text, each stopped (SIGTERM) at the end."""
    from nac_onboard.child_process import AgentProcess

    started: list[AgentProcess] = []

    def start(config_text: str, name: str = "agent", env: dict | None = None) -> AgentProcess:
        path = tmp_path / f"{name}-{len(started)}.toml"
        path.write_text(config_text)
        agent = AgentProcess(path, env=env)
        started.append(agent)
        return agent.start()

    yield start
    for agent in started:
        agent.stop()
        assert not agent.alive()
