import shutil

import pytest

from ground.view.serve import CHROMIUM_FLAGS, chromium
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


CHROMEDRIVER = shutil.which("chromedriver")
needs_browser = pytest.mark.skipif(not (chromium() and CHROMEDRIVER),
                                   reason="Chromium and chromedriver are not installed (.ci/run installs them)")


@pytest.fixture
def browser(tmp_path):
    """Debian's headless Chromium through its chromedriver, quit when the test ends."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium()
    for flag in [*CHROMIUM_FLAGS, "--window-size=1400,860", f"--user-data-dir={tmp_path / 'profile'}"]:
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(30)
    yield driver
    driver.quit()
