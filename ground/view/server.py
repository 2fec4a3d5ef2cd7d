"""The view's server: the page (static files shipped in the package), the run's state, its records for a replay,
and the same records live as Server-Sent Events. One RunFollower feeds all of it; the server never writes to
the run.

    GET /                     the page
    GET /api/state            vehicles, roles, missions, what is missing or damaged, live or not
    GET /api/records?after=S  every frame after index S (a replay loads them all at once)
    GET /api/stream?after=S   the frames after S, then each new batch as it is read (SSE; a reconnecting
                              browser resumes from Last-Event-ID)

A page that cannot keep up gets bigger batches, never fewer records: it draws the latest state once per
animation frame, so it drops frames, not records.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import orjson
from aiohttp import web

from ground.view.records import RunFollower
from nac_onboard.errors import NacError, OperationFailed

log = logging.getLogger(__name__)
STATIC = Path(__file__).parent / "static"
POLL_S = 0.1  # how often a live run's files are read: 10 updates a second
HEARTBEAT_S = 15.0  # an SSE comment when nothing new: proxies and browsers keep the stream open


class ViewServer:
    def __init__(self, run_dir: str | Path | None, live: bool, title: str = "", sources: list | None = None):
        self.follower = RunFollower(None if run_dir is None else Path(run_dir))
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
        app = web.Application()
        app.router.add_get("/", self._index)
        app.router.add_get("/api/state", self._state)
        app.router.add_get("/api/records", self._records)
        app.router.add_get("/api/stream", self._stream)
        app.router.add_static("/static/", STATIC)
        return app

    async def start(self, host: str, port: int) -> str:
        """Serve on host:port (0: any free port); returns the page's URL. A taken port: OperationFailed naming it."""
        self._changed = asyncio.Event()
        self._runner = web.AppRunner(self.app(), access_log=None, shutdown_timeout=2.0)
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

    # ---- handlers ---------------------------------------------------------------------------------------
    async def _index(self, request: web.Request) -> web.FileResponse:
        return web.FileResponse(STATIC / "index.html")

    async def _state(self, request: web.Request) -> web.Response:
        f = self.follower
        origin = None if f.origin is None else {"lat_deg": f.origin.lat_deg, "lon_deg": f.origin.lon_deg,
                                                  "alt_m": f.origin.alt_m}
        return web.json_response({"title": self.title, "live": self.live, "vehicles": f.vehicles, "origin": origin,
                                  "missions": f.missions_m(), "problems": f.problems, "missing": f.missing(),
                                  "records": f.record_count})

    async def _records(self, request: web.Request) -> web.Response:
        after = _after(request)
        return web.Response(body=orjson.dumps(self.follower.records[after + 1:]), content_type="application/json")

    async def _stream(self, request: web.Request) -> web.StreamResponse:
        after = _after(request)
        response = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-cache"})
        await response.prepare(request)
        records = self.follower.records
        try:
            while not self._closing:
                changed = self._changed
                if len(records) > after + 1:
                    batch = records[after + 1:]
                    after = batch[-1]["s"]
                    await response.write(b"id: %d\nevent: records\ndata: %s\n\n" % (after, orjson.dumps(batch)))
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


def _after(request: web.Request) -> int:
    text = request.headers.get("Last-Event-ID") or request.query.get("after", "-1")
    try:
        return max(int(text), -1)
    except ValueError:
        raise web.HTTPBadRequest(text=f"after: expected a record index, got {text!r}") from None
