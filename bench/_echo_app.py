"""The reference of bench_service: a bare FastAPI app that parses a JSON body and echoes it."""

from __future__ import annotations

import time
from typing import Annotated, Any

from fastapi import Body, FastAPI
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send


class _ServerTiming:
    """The same `Server-Timing: app;dur=<ms>` header the detcal app adds."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        start = time.perf_counter()

        async def timed(message: Message) -> None:
            if message["type"] == "http.response.start":
                dur = (time.perf_counter() - start) * 1000.0
                timing = (b"server-timing", f"app;dur={dur:.3f}".encode())
                message = {**message, "headers": [*message.get("headers", []), timing]}
            await send(message)

        await self.app(scope, receive, timed)


app = FastAPI()
app.add_middleware(_ServerTiming)


@app.post("/echo")
def echo(payload: Annotated[dict[str, Any], Body()]) -> JSONResponse:
    """Parse the JSON body and send it back."""
    return JSONResponse(payload)
