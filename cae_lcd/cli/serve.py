"""``cae-lcd serve --state DIR``: the fleet server (``cae_lcd.fleet.server``) on uvicorn, on loopback by default.

The admin token (it registers robots) comes from ``--admin-token``, else the ``CAE_LCD_ADMIN_TOKEN`` environment
variable, else a random one printed once on start. A server stopped or killed continues from ``--state``.
"""

from __future__ import annotations

import logging
import os
import secrets
import sys
from typing import Any

from cae_lcd.core.conf import ConfigError, load_conf_file

__all__ = ["add_parser", "run", "serve", "admin_token", "TOKEN_ENV"]

log = logging.getLogger("cae_lcd.serve")

TOKEN_ENV = "CAE_LCD_ADMIN_TOKEN"  #: environment variable holding the admin token


def admin_token(given: str | None) -> tuple[str, bool]:
    """The admin token: ``given``, else ``$CAE_LCD_ADMIN_TOKEN``, else a new random one.

    Returns:
        ``(token, generated)``.
    """
    token = given or os.environ.get(TOKEN_ENV, "")
    return (token, False) if token else (secrets.token_urlsafe(32), True)


def serve(state: str, host: str = "127.0.0.1", port: int = 8765, admin: str | None = None,
          config: str | None = None, store: str | None = None, workers: int = 1,
          ray_address: str | None = None) -> None:
    """Runs the fleet server until interrupted.

    Args:
        state: the state folder (created, or continued).
        host: interface to listen on (loopback by default: put a TLS proxy in front to serve a network).
        port: TCP port.
        admin: the admin token (None: the environment's, else a generated one printed once).
        config: YAML with ``service`` (``FleetService.default_conf``) and ``recognition``
            (``FleetRecognizer.default_conf``) sections.
        store: a ``postgresql://`` URL (shared by several servers) or a SQLite file (None: ``STATE/fleet.sqlite``).
        workers: > 1: robots sharded over that many Ray workers (a local Ray unless ``ray_address``).
        ray_address: a Ray cluster to run the workers on.

    Raises:
        ConfigError: a bad config, port or state folder.
    """
    import uvicorn  # here: the CLI's other commands do not load the fleet's dependencies (the [fleet] extra)
    from cae_lcd.core.threads import reexec_with_server_malloc
    from cae_lcd.fleet.runner import server_config
    from cae_lcd.fleet.server import create_app

    if not 0 < port < 65536:
        raise ConfigError(f"--port must be in 1..65535; got {port}")
    conf = load_conf_file(config) if config else {}
    unknown = set(conf) - {"service", "recognition"}
    if unknown:
        raise ConfigError(f"{config}: unknown sections {sorted(unknown)}; allowed: service, recognition")
    reexec_with_server_malloc()  # once the arguments are checked, before anything starts or is written (cae_lcd.core.threads)
    token, generated = admin_token(admin)
    app = create_app(state, token, conf.get("service"), conf.get("recognition"), store=store, workers=workers,
                     ray_address=ray_address)
    if generated:
        print(f"admin token (shown once; set {TOKEN_ENV} to choose one): {token}", file=sys.stderr, flush=True)
    log.info("fleet server on http://%s:%d, state in %s%s", host, port, state,
             f", store {store.split('@')[-1]}" if store else "")
    uvicorn.Server(server_config(app, host, port)).run()


def add_parser(sub: Any) -> None:
    from cae_lcd.core.cli import add_missing_extra, api_defaults

    try:
        import fastapi  # noqa: F401 - only whether the [fleet] extra is installed
    except ImportError as err:
        add_missing_extra(sub, "serve", "fleet", err)
        return
    d = api_defaults(serve)
    p = sub.add_parser("serve", help="run the fleet server (robots submit keyframes over HTTP)",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--state", required=True, help="state folder (created, or continued after a stop or a crash)")
    p.add_argument("--host", default=d["host"], help=f"interface (default: {d['host']}, loopback only)")
    p.add_argument("--port", type=int, default=d["port"], help=f"TCP port (default: {d['port']})")
    p.add_argument("--admin-token", default=d["admin"],
                   help=f"admin token (default: ${TOKEN_ENV}, else generated and printed once)")
    p.add_argument("--config", default=d["config"], help="YAML with 'service' and 'recognition' sections")
    p.add_argument("--store", default=d["store"],
                   help="postgresql://USER@HOST:PORT/DB (shared by replicas) or a SQLite file "
                        "(default: STATE/fleet.sqlite)")
    p.add_argument("--workers", type=int, default=d["workers"],
                   help=f"> 1: robots sharded over that many Ray workers (default: {d['workers']}, in this process)")
    p.add_argument("--ray-address", default=d["ray_address"], help="a Ray cluster for the workers (default: local)")
    p.set_defaults(func=run)


def run(args: Any) -> None:
    serve(args.state, args.host, args.port, args.admin_token, args.config, args.store, args.workers,
          args.ray_address)
