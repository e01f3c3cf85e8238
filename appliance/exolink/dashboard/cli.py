"""`exolink dashboard`: the web app on this laptop, talking to the appliance like the CLI.

asyncio and aiohttp are imported when the command runs, not whenever `exolink` starts.
"""

from __future__ import annotations

import argparse
import signal
import sys

from exolink.cli.errors import EXIT_USAGE, fail
from exolink.cli.options import common, decimal, guard, integer
from exolink.client import remote


@guard
def cmd_dashboard(args: argparse.Namespace) -> int:
    import asyncio  # lazy: the dashboard command only: the others start without asyncio

    from exolink.dashboard import guard, server  # heavy: aiohttp; `exolink dashboard` only
    from exolink.dashboard.hub import Hub  # heavy: the dashboard's Zenoh side; `dashboard` only

    try:
        hosts = guard.Hosts(args.port, args.allow_host)
    except ValueError as exc:
        return fail(f"--allow-host: {exc}", EXIT_USAGE)
    with remote(args) as r:
        hub = Hub(r, rate_hz=args.rate)

        def ready(url: str) -> None:
            sys.stdout.write(f"dashboard on {url} (appliance {r.device} at {r.at}, {hub.role})\n")
            sys.stdout.flush()
            if not args.no_browser:
                server.open_browser(url)

        async def main() -> None:
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
            await server.serve(hub, args.host, args.port, stop, ready, hosts)

        try:
            asyncio.run(main())
        except BrokenPipeError:  # stdout closed (`exolink dashboard | head -1`): not the port
            raise
        except OSError as exc:  # the port is taken, the address is not this machine's
            return fail(
                f"cannot serve on {args.host}:{args.port}: {exc.strerror or exc}", EXIT_USAGE
            )
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "dashboard",
        parents=[common()],
        help="the web dashboard on this laptop (http://127.0.0.1:8080)",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (127.0.0.1)")
    p.add_argument("--port", type=integer, default=8080, help="port to serve on (8080)")
    p.add_argument(
        "--allow-host",
        action="append",
        default=[],
        metavar="NAME",
        help="also answer to this Host name (NAME or NAME:PORT; <hostname>: this machine's, "
        "<address>: the address a request came in on); loopback names always work",
    )
    p.add_argument("--no-browser", action="store_true", help="do not open a browser")
    p.add_argument("--rate", type=decimal, default=25.0, help="frames per second to each page (25)")
    p.set_defaults(func=cmd_dashboard)
