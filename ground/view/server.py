"""The view's server: the page (static files shipped in the package), the run's state, its records for a replay,
and the same records live as Server-Sent Events. One RunFollower feeds all of it; the server never writes to
the run.

    GET /                     the page
    GET /api/state            vehicles, roles, missions, what is missing or damaged, live or not
    GET /api/records?after=S  the frames after index S, at most MAX_RESPONSE_BYTES of them (at least one);
                              header X-More-Records: yes when there are more (the page asks again from the last)
    GET /api/stream?after=S   the frames after S, then each new batch as it is read (SSE, events of at most
                              MAX_RESPONSE_BYTES; a reconnecting browser resumes from Last-Event-ID)

A page that cannot keep up gets bigger batches, never fewer records: it draws the latest state once per
animation frame, so it drops frames, not records.

Every request's Host header is checked before anything is answered (DNS rebinding: a page of another site whose
name is made to point at this machine must not read the vehicles' positions): it must name the address the server
listens on, a localhost form when that is loopback, any IP address when it is every interface (a name, not an
address, is what a rebinding page sends), or one of the names given in `allowed_hosts`; anything else gets 421. A
request that carries an Origin header (a browser's cross-site request) must come from such a host too, else 403.
Nothing here changes state: every route is GET.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import socket
from pathlib import Path
from urllib.parse import urlsplit

import orjson
from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError

from ground.view.records import RunFollower
from nac_onboard.errors import NacError, OperationFailed

log = logging.getLogger(__name__)
STATIC = Path(__file__).parent / "static"
POLL_S = 0.1  # how often a live run's files are read: 10 updates a second
HEARTBEAT_S = 15.0  # an SSE comment when nothing new: proxies and browsers keep the stream open
MAX_RESPONSE_BYTES = 16 << 20  # of frames in one /api/records answer or one SSE event (a frame is bounded too)


class _RequestLog(logging.Logger):
    """aiohttp's log of the requests it serves: one it could not parse (no Host, a malformed line: hostile or
    broken input) is a one-line warning, not a traceback; anything else as aiohttp logs it."""

    def exception(self, msg, *args, exc_info=True, **kwargs):
        if isinstance(exc_info, HttpProcessingError):
            self.warning(msg + ": %s", *args, str(exc_info).strip().replace("\n", " "))
        else:
            super().exception(msg, *args, exc_info=exc_info, **kwargs)


REQUEST_LOG = _RequestLog("ground.view.http")
REQUEST_LOG.parent = log


LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback"})


class ViewServer:
    def __init__(self, run_dir: str | Path | None, live: bool, title: str = "", sources: list | None = None,
                 allowed_hosts: list[str] | tuple[str, ...] = ()):
        self.follower = RunFollower(None if run_dir is None else Path(run_dir))
        self.allowed_hosts = {_host_name(h) for h in allowed_hosts}  # names the page may be reached by, besides
        self.bind_host = "127.0.0.1"  # ... the address it listens on (set by start())
        self.live = live
        self.sources = sources or []  # live sources beside the files: MavlinkSource
        self.title = title or (Path(run_dir).name if run_dir is not None else "live")
        self._changed: asyncio.Event | None = None  # made in start(), on the server loop
        self._runner: web.AppRunner | None = None
        self._closing = False
        self._poller: asyncio.Task | None = None
        if not live:
            self.follower.finish()

    def app(self) -> web.Application:
        app = web.Application(middlewares=[self._check_host])
        app.router.add_get("/", self._index)
        app.router.add_get("/api/state", self._state)
        app.router.add_get("/api/records", self._records)
        app.router.add_get("/api/stream", self._stream)
        app.router.add_static("/static/", STATIC)
        return app

    async def start(self, host: str, port: int) -> str:
        """Serve on host:port (0: any free port); returns the page's URL. A taken port: OperationFailed naming it."""
        self._changed = asyncio.Event()
        self.bind_host = host
        self._runner = web.AppRunner(self.app(), access_log=None, shutdown_timeout=2.0, logger=REQUEST_LOG)
        await self._runner.setup()
        site = web.TCPSite(self._runner, host, port)
        try:
            await site.start()
        except OSError as err:
            await self._runner.cleanup()
            raise OperationFailed(f"cannot serve the view on {host}:{port}: {err.strerror or err}") from None
        bound = self._runner.addresses[0][1]  # the port chosen when 0 was asked
        if self.live:
            self._poller = asyncio.create_task(self._poll())
        return f"http://{host if ':' not in host else f'[{host}]'}:{bound}/"

    async def stop(self) -> None:
        self._closing = True  # open streams end at once instead of holding the shutdown
        if self._changed is not None:
            self._changed.set()
        if self._poller is not None:
            self._poller.cancel()
        for source in self.sources:
            source.close()
        if self._runner is not None:
            await self._runner.cleanup()

    async def _poll(self) -> None:
        while True:
            added = 0
            for source in self.sources:
                try:
                    added += source.pump(self.follower)
                except (NacError, OSError) as err:  # a link that failed: said on the page, the rest goes on
                    log.warning("view source: %s", err)
                    if len(self.follower.problems) < 200:
                        self.follower.problems.append(f"live source: {err}")
            if self.follower.poll() or added:
                self._changed.set()
                self._changed = asyncio.Event()
            await asyncio.sleep(POLL_S)

    # ---- who may ask ------------------------------------------------------------------------------------
    def host_allowed(self, name: str) -> bool:
        """Whether a request naming `name` (a Host header's host, without the port) reaches this view on
        purpose: the listening address, localhost forms on a loopback bind, any address on an every-interface
        bind, or a name given."""
        name = _host_name(name)
        if not name:
            return False
        if name in self.allowed_hosts:
            return True
        bind = _host_name(self.bind_host)
        if name == bind:
            return True
        bind_ip, name_ip = _ip(bind), _ip(name)
        if bind in LOOPBACK_NAMES or (bind_ip is not None and bind_ip.is_loopback):
            return name in LOOPBACK_NAMES or (name_ip is not None and name_ip.is_loopback)
        if bind_ip is not None and bind_ip.is_unspecified:  # every interface: reached by any of its addresses
            return name_ip is not None or name in LOOPBACK_NAMES or name == _host_name(socket.gethostname())
        return False

    @web.middleware
    async def _check_host(self, request: web.Request, handler):
        host = request.headers.get("Host", "")
        if not self.host_allowed(_split_port(host)):
            raise web.HTTPMisdirectedRequest(
                text=f"this NAC view does not answer to the host {host[:100]!r}: open it by the address it "
                     f"listens on ({self.bind_host}){', localhost' if self._loopback() else ''}"
                     f"{', or ' + ', '.join(sorted(self.allowed_hosts)) if self.allowed_hosts else ''}\n")
        origin = request.headers.get("Origin")
        if origin is not None and not self.host_allowed(urlsplit(origin).hostname or ""):
            raise web.HTTPForbidden(text=f"this NAC view refuses requests from pages of {origin[:100]!r}\n")
        return await handler(request)

    def _loopback(self) -> bool:
        bind = _host_name(self.bind_host)
        return bind in LOOPBACK_NAMES or bool((ip := _ip(bind)) and ip.is_loopback)

    # ---- handlers ---------------------------------------------------------------------------------------
    async def _index(self, request: web.Request) -> web.FileResponse:
        return web.FileResponse(STATIC / "index.html")

    async def _state(self, request: web.Request) -> web.Response:
        f = self.follower
        origin = None if f.origin is None else {"lat_deg": f.origin.lat_deg, "lon_deg": f.origin.lon_deg,
                                                  "alt_m": f.origin.alt_m}
        return web.json_response({"title": self.title, "live": self.live, "vehicles": f.vehicles, "origin": origin,
                                  "missions": f.missions_m(), "problems": f.problems, "missing": f.missing(),
                                  "records": f.record_count, "speedup": f.speedup})

    async def _records(self, request: web.Request) -> web.Response:
        body, _, more = _page(self.follower.records, _after(request))
        return web.Response(body=body, content_type="application/json",
                            headers={"X-More-Records": "yes" if more else "no", "Cache-Control": "no-store"})

    async def _stream(self, request: web.Request) -> web.StreamResponse:
        after = _after(request)
        response = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-cache"})
        await response.prepare(request)
        records = self.follower.records
        try:
            while not self._closing:
                changed = self._changed
                if len(records) > after + 1:
                    body, after, more = _page(records, after)
                    await response.write(b"id: %d\nevent: records\ndata: %s\n\n" % (after, body))
                    if more:
                        continue  # the rest at once, an event at a time
                elif not self.live:
                    await response.write(b"event: end\ndata: {}\n\n")
                    break
                try:
                    await asyncio.wait_for(changed.wait(), HEARTBEAT_S)
                except asyncio.TimeoutError:
                    await response.write(b": still here\n\n")
        except (ConnectionResetError, asyncio.CancelledError):
            pass  # the browser left; it resumes from its Last-Event-ID when it comes back
        return response


def _page(records: list[dict], after: int) -> tuple[bytes, int, bool]:
    """The frames after index `after` as a JSON list of at most MAX_RESPONSE_BYTES (at least one frame), the
    last index in it, and whether more follow."""
    parts, size, last = [], 2, after
    for k in range(after + 1, len(records)):
        frame = records[k]
        encoded = orjson.dumps(frame)
        if parts and size + len(encoded) + 1 > MAX_RESPONSE_BYTES:
            return b"[" + b",".join(parts) + b"]", last, True
        parts.append(encoded)
        size += len(encoded) + 1
        last = frame["s"]
    return b"[" + b",".join(parts) + b"]", last, False


def _split_port(host: str) -> str:
    """A Host header's host: "[::1]:8765" -> "::1", "example.org:80" -> "example.org"."""
    if host.startswith("["):
        return host[1:host.find("]")] if "]" in host else ""
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def _host_name(host: str) -> str:
    return host.strip().strip("[]").rstrip(".").lower()


def _ip(name: str):
    try:
        return ipaddress.ip_address(name)
    except ValueError:
        return None


def _after(request: web.Request) -> int:
    text = request.headers.get("Last-Event-ID") or request.query.get("after", "-1")
    try:
        return max(int(text), -1)
    except ValueError:
        raise web.HTTPBadRequest(text=f"after: expected a record index, got {text!r}") from None
