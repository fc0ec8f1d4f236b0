"""`triswarm pki`: the swarm's certificates and its Zenoh configurations with mTLS and access control."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from . import pki
from .errors import UserError, console, user_errors

pki_app = typer.Typer(no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                      help="The swarm's certificates (a CA, routers, agents, the ground station) and Zenoh configs with "
                           "mTLS and access control.")


@pki_app.command("init")
def init(
    out: Annotated[Path, typer.Option("--out", help="Folder to write into (made 0700 if new).")],
    swarm: Annotated[str, typer.Option("--swarm", help="The swarm's name: its keys are triswarm/<swarm>/... "
                                                       "(the companions' --swarm, by default the plan's name).")],
    drones: Annotated[int, typer.Option("--drones", help="Number of drones: agents 1..N get a certificate.")],
    router: Annotated[list[str], typer.Option("--router", help="A router as the clients reach it, HOST[:PORT] "
                                                               f"(default port {pki.DEFAULT_ROUTER_PORT}; repeat).")],
    days: Annotated[int, typer.Option("--days", help="Validity of the router, agent and gcs certificates, in days "
                                                     f"(the CA: {pki.CA_DAYS}).")] = pki.DEFAULT_DAYS,
    force: Annotated[bool, typer.Option("--force", help="Start again: a new CA and new certificates for all.")] = False,
    cert_dir: Annotated[Optional[Path], typer.Option("--cert-dir", help="Where the certificates will be on the machines "
                                                                        "(the paths in the configs; default: --out).")] = None,
    listen: Annotated[str, typer.Option("--listen", help="Address the routers listen on.")] = "0.0.0.0",
) -> None:
    """Make the swarm CA, router and client certificates, and the Zenoh configs that use them.

    Writes OUT/ca.pem (OUT/ca.key stays with the operator), OUT/router-<host>.{pem,key},
    OUT/agent-<i>.{pem,key}, OUT/gcs.{pem,key}, and OUT/zenoh/router-<host>.json5,
    OUT/zenoh/agent-<i>.json5, OUT/zenoh/gcs.json5. Re-running keeps the CA and every certificate
    still valid, makes what is missing and rewrites the configs."""
    with user_errors():
        if not router:
            raise UserError("at least one --router HOST[:PORT] is needed")
        report = pki.init(out, swarm, drones, router, days=days, force=force, cert_dir=cert_dir, listen_host=listen)
        made = sorted({p.name for p in report.made if p.suffix == ".pem"})
        kept = sorted({p.name for p in report.kept})
        console.print(f"certificates made: {', '.join(made) if made else 'none'}", highlight=False)
        if kept:
            console.print(f"certificates kept (still valid): {', '.join(kept)}", highlight=False)
        console.print(f"Zenoh configs: {out / 'zenoh'} ({len(report.configs)} files)", highlight=False)
        console.print(f"Keep {out / 'ca.key'} with the operator: copy to a drone only ca.pem, agent-<i>.pem, "
                      "agent-<i>.key and zenoh/agent-<i>.json5.", highlight=False)
