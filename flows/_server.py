"""Entry point of the embedded Prefect server child process: uvicorn serving Prefect's API, plus a
watchdog that ends the server when the ms3d process that started it dies (even by SIGKILL), so a
killed run never leaves a server holding the work dir's database.

    python -m flows._server PORT [HOST]

HOST defaults to 127.0.0.1 (``flows.runtime.LOOPBACK``): the API has no authentication.
"""

from __future__ import annotations

import os
import sys
import threading
import time


def _watch_parent(parent: int, period_s: float = 1.0) -> None:
    while True:
        time.sleep(period_s)
        if os.getppid() != parent:
            os._exit(0)


def main(argv: list[str]) -> None:
    import uvicorn

    from flows.runtime import LOOPBACK

    port = int(argv[0])
    host = argv[1] if len(argv) > 1 else LOOPBACK
    threading.Thread(target=_watch_parent, args=(os.getppid(),), daemon=True).start()
    uvicorn.run("prefect.server.api.server:create_app", factory=True, host=host, port=port,
                log_level="error", lifespan="on")


if __name__ == "__main__":
    main(sys.argv[1:])
