"""The measurement service: ``serve`` and ``records export``."""

from __future__ import annotations

import typer

from .app import (
    app,
    fail,
    friendly,
    log,
)

records_app = typer.Typer(no_args_is_help=True, help="The service's measurement records.")
app.add_typer(records_app, name="records")


@app.command("serve")
@friendly
def serve_cmd(
    config: str = typer.Option(None, "--config", help="Cell file (TOML); default: the bundled "
                               "Table 1 cell (data/cell_table1.toml in the package)."),
    host: str = typer.Option("127.0.0.1", help="Address to bind (0.0.0.0: every interface; "
                             "then use TLS and a strong token)."),
    port: int = typer.Option(8000, min=0, max=65535, help="Port."),
    workers: int = typer.Option(None, min=1, help="Worker processes (default: the cell file's, "
                                "0 there = one per core)."),
    ssl_certfile: str = typer.Option(None, help="TLS certificate (PEM); with --ssl-keyfile "
                                     "the service speaks HTTPS."),
    ssl_keyfile: str = typer.Option(None, help="TLS private key (PEM, unencrypted)."),
    ssl_ca_certs: str = typer.Option(None, help="CA bundle to verify client certificates."),
    ssl_cert_reqs: int = typer.Option(0, min=0, max=2, help="Client certificates: 0 none, "
                                      "1 optional, 2 required (mutual TLS)."),
    log_level: str = typer.Option("info", help="uvicorn log level."),
):
    """The measurement service for the robot controller (HTTP API, docs/service.md). The bearer
    token comes from the environment variable CUTTERPOSE_TOKEN or the cell file's
    service.token_file, never from the command line."""
    import dataclasses

    try:
        from ..service.server import run
    except ImportError as e:
        fail(f"the service needs its extra: pip install 'cutterpose[service]' ({e})")
    from ..service.config import load_cell

    cell = load_cell(config)
    if workers:
        cell = dataclasses.replace(cell, service=dataclasses.replace(cell.service,
                                                                     workers=workers))
    if bool(ssl_certfile) != bool(ssl_keyfile):
        fail("TLS needs both --ssl-certfile and --ssl-keyfile")
    log(f"cell {cell.name!r}: camera {cell.camera_source} "
        f"{cell.camera.image_size_px[0]} x {cell.camera.image_size_px[1]} px, "
        f"{cell.service.workers} workers, data in {cell.service.data_dir}")
    # the cell's timeouts and connection limits (docs/service.md); a locked or corrupt
    # record stops the start here with its reason
    run(cell, host=host, port=port, log_level=log_level, ssl_certfile=ssl_certfile,
        ssl_keyfile=ssl_keyfile, ssl_ca_certs=ssl_ca_certs, ssl_cert_reqs=ssl_cert_reqs)


@records_app.command("export")
@friendly
def records_export_cmd(
    since: str = typer.Option(None, help="ISO 8601 time (UTC if no zone), inclusive; default "
                              "everything."),
    fmt: str = typer.Option("csv", "--format", help="csv (one row per measurement) or json."),
    out: str = typer.Option(None, "--out", help="Output file (default stdout)."),
    config: str = typer.Option(None, "--config", help="Cell file naming the data directory."),
    data_dir: str = typer.Option(None, "--data-dir", help="Data directory (wins over the cell "
                                 "file and CUTTERPOSE_DATA_DIR)."),
):
    """Write the service's measurement records for the quality engineer."""
    from pathlib import Path

    from ..service.config import load_cell
    from ..service.records import export_records

    folder = Path(data_dir) if data_dir else load_cell(config, need_token=False).service.data_dir
    text, n = export_records(folder, since, fmt)
    if out:
        Path(out).write_text(text)
        log(f"wrote {n} records to {out}")
    else:
        typer.echo(text, nl=False)
