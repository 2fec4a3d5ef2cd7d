"""Serving the view: in a thread beside an experiment, or in the foreground for a finished run; and a
screenshot of the page by headless Chromium (Debian's `chromium`), when it is installed."""

from __future__ import annotations

import asyncio
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

from ground.view.server import ViewServer
from nac_onboard.address import parse_host_port
from nac_onboard.child_process import die_with_parent_preexec
from nac_onboard.errors import BadInput, OperationFailed

DEFAULT_ADDRESS = "127.0.0.1:8765"  # loopback unless asked: the page shows where the vehicles are
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--hide-scrollbars"]


class ViewThread:
    """A ViewServer on its own event loop in a daemon thread: start() returns the URL, stop() ends it."""

    def __init__(self, server: ViewServer, address: str = DEFAULT_ADDRESS):
        self.server = server
        self.host, self.port = parse_host_port(address, "view address", allow_port_zero=True)
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="view", daemon=True)
        self.url = ""

    def start(self) -> str:
        self.thread.start()
        future = asyncio.run_coroutine_threadsafe(self.server.start(self.host, self.port), self.loop)
        try:
            self.url = future.result(timeout=10.0)
        except Exception:
            self.loop.call_soon_threadsafe(self.loop.stop)
            raise
        return self.url

    def stop(self) -> None:
        if self.thread.is_alive():
            asyncio.run_coroutine_threadsafe(self.server.stop(), self.loop).result(timeout=10.0)
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(10.0)


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


LIVE_SCREENSHOT_LISTEN_S = 10.0  # --live --screenshot: how long to wait for a first vehicle before the picture


def screenshot(url: str, path: Path, width: int = 1400, height: int = 860, timeout_s: float = 60.0) -> Path:
    """The page at the run's end as a PNG, by headless Chromium (it waits for the page's scripts, virtual time;
    a snapshot: no live stream, which would keep the network busy for ever)."""
    url += ("&" if "?" in url else "?") + "at=end&snapshot=1"
    browser = chromium()
    if browser is None:
        raise OperationFailed("no Chromium to take the screenshot with (Debian: apt-get install chromium)")
    profile = path.parent / ".chromium-profile"
    try:
        done = subprocess.run([browser, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--screenshot={path}",
                               f"--window-size={width},{height}", "--virtual-time-budget=4000", url],
                              capture_output=True, text=True, timeout=timeout_s,
                              preexec_fn=die_with_parent_preexec())  # a killed runner takes it along
    except subprocess.TimeoutExpired:
        raise OperationFailed(f"Chromium took more than {timeout_s:g} s to render {url}") from None
    finally:
        shutil.rmtree(profile, ignore_errors=True)
    if done.returncode != 0 or not path.exists():
        raise OperationFailed(f"Chromium could not take the screenshot: {done.stderr.strip()[-300:]}")
    return path


def replay(run_dir: Path, address: str, screenshot_path: Path | None = None, out=None, live: bool = False,
           allowed_hosts: tuple[str, ...] = ()) -> int:
    """Serve a run until Ctrl-C: finished (replay), or followed as it is written (live). With screenshot_path,
    save the page at the run's end and stop. The page answers to the address it listens on (and localhost on
    loopback) and to `allowed_hosts`, nothing else (ViewServer)."""
    out = out or sys.stdout
    if not Path(run_dir).is_dir():
        raise BadInput(f"{run_dir}: no such run directory")
    server = ViewServer(run_dir, live=live, allowed_hosts=allowed_hosts)
    if not live and not server.follower.records:
        raise BadInput(f"{run_dir}: no NAC records here (VEHICLE/agent.jsonl, throughput.jsonl, compute.jsonl)")
    viewer = ViewThread(server, address)
    url = viewer.start()
    missing = server.follower.missing()
    announce = (f"view: {url} ({'live' if live else f'{server.follower.record_count} records'}"
                + (f"; missing: {'; '.join(missing)}" if missing and not live else "") + ")")
    then = None
    if screenshot_path is not None:
        def then():
            print(f"view: {screenshot(url, Path(screenshot_path))}", file=out, flush=True)
    return _serve(viewer, announce, out, then)


def _serve(viewer: ViewThread, announce: str, out, then=None) -> int:
    """Say where the page is; then do `then` (a screenshot) or serve until Ctrl-C; stop the server either way."""
    try:
        print(announce, file=out, flush=True)
        if then is not None:
            then()
        else:
            threading.Event().wait()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return 0


def watch(uris: list[str], feed: str | None, run_dir: Path | None, address: str, out=None,
          allowed_hosts: tuple[str, ...] = (), screenshot_path: Path | None = None,
          listen_s: float = LIVE_SCREENSHOT_LISTEN_S) -> int:
    """Vehicles live over MAVLink (and the master agent's state feed), with a run directory's files when one is
    given; until Ctrl-C. With screenshot_path: listen until something is drawn (at most listen_s), save the page as
    a PNG and stop; when nothing was heard, say so beside the picture of the empty map."""
    from ground.view.mavlink_source import MavlinkSource

    out = out or sys.stdout
    if not uris and not feed:
        raise BadInput("view --live: give at least one --connect URI or a --feed HOST:PORT")
    if feed:
        parse_host_port(feed, "--feed")
    if run_dir is not None and not Path(run_dir).is_dir():
        raise BadInput(f"{run_dir}: no such run directory")
    source = MavlinkSource(uris, feed)
    server = ViewServer(run_dir, live=True, title="live", sources=[source], allowed_hosts=allowed_hosts)
    viewer = ViewThread(server, address)
    try:
        url = viewer.start()
    except BaseException:
        source.close()
        raise
    watched = ", ".join(uris + ([f"feed {feed}"] if feed else []))
    then = None
    if screenshot_path is not None:
        def then():
            deadline = time.monotonic() + listen_s
            while server.follower.record_count == 0 and time.monotonic() < deadline:
                time.sleep(0.2)
            if server.follower.record_count == 0:
                print(f"view: nothing heard on {watched} within {listen_s:g} s: the picture shows an empty map",
                      file=out, flush=True)
            print(f"view: {screenshot(url, Path(screenshot_path))}", file=out, flush=True)
    return _serve(viewer, f"view: {url} (live: {watched})", out, then)
