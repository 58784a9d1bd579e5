"""`ssg view`: scenes, sampled trees and parses in the browser (ssgc.view; docs/view.md)."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated, Any

import typer

from ssgc.errors import SsgError

from .app import AllowOutside, _command, _warnings_about, app, err

SERVE_HOST = "127.0.0.1"  # this machine only: the page is for the user who runs ssg


@app.command(short_help="An interactive 3-D page in the browser.")
@_command
def view(
    source: Annotated[
        Path,
        typer.Argument(
            help="A scene JSON, a directory of them, an `ssg parse` result, or a sink-format "
            "YAML dataset (with -g).",
            show_default=False,
        ),
    ],
    output: Annotated[
        Path | None,
        typer.Option(
            "-o", "--output", help="Write the page here (.html); needed unless --open/--serve."
        ),
    ] = None,
    grammar: Annotated[
        Path | None,
        typer.Option("-g", "--grammar", help="Grammar for the objects' shapes (optional)."),
    ] = None,
    open_it: Annotated[
        bool, typer.Option("--open", help="Open the page in the default browser.")
    ] = False,
    serve: Annotated[
        bool,
        typer.Option("--serve", help="Serve the page on 127.0.0.1 until Ctrl-C."),
    ] = False,
    port: Annotated[
        int | None,
        typer.Option(
            "--port", min=0, max=65535, help="--serve: the port (default 8000; 0: any free)."
        ),
    ] = None,
    quiet: Annotated[bool, typer.Option("-q", "--quiet", help="No summary line.")] = False,
    allow_outside_files: AllowOutside = False,
) -> None:
    """An interactive 3-D page: step through scenes, click an object for its tree path and
    rule scores.  One self-contained HTML file; nothing is fetched from the network."""
    from ssgc.compile import load_grammar
    from ssgc.io.outputs import lock_outputs, write_output_text
    from ssgc.view.page import check_page, view_page

    if output is None and not (open_it or serve):
        raise SsgError.single("say where the page goes: -o PAGE.html, or --open or --serve")
    if port is not None and not serve:
        raise SsgError.single("--port is the port of --serve, which is not given")
    dest = None if output is None else check_page(output, source, grammar)
    # the port is taken before any work: one in use is refused with no page written
    server = _bind(8000 if port is None else port) if serve else None
    try:
        with lock_outputs([dest]):
            allow = allow_outside_files
            g = None if grammar is None else load_grammar(grammar, allow_outside=allow)
            with _warnings_about(source):
                html, count = view_page(source, g)
            if dest is not None:
                write_output_text(dest, html)
        if not quiet:
            where = dest.name if dest is not None else "the page"
            err.print(f"{count} scene(s) of {source} on {where}", markup=False, highlight=False)
        if open_it:
            _open(html, None if dest is None or dest.stream else dest.target, output)
        if server is not None:
            _serve(server, html.encode("utf-8"))
    finally:
        if server is not None:
            server.server_close()


def _open(html: str, page: Path | None, given: Path | None) -> None:
    """The written page `page`, or (without one) a temporary copy that lives until the browser
    has read it.  No browser is an error only for that copy: a written page is there, and the
    user is told where (`given`, as typed), with a warning and exit 0 (docs/view.md)."""
    import time
    import webbrowser

    with tempfile.TemporaryDirectory(prefix="ssg-view-") as tmp:
        temporary = page is None
        if page is None:
            page = Path(tmp) / "view.html"
            page.write_text(html, encoding="utf-8")
        if webbrowser.open(page.resolve().as_uri()):
            time.sleep(3.0 if temporary else 0.0)
        elif temporary:
            raise SsgError.single("no browser found to open the page: write it with -o PAGE.html")
        else:
            err.print(
                f"{given}: warning: no browser found to open the page; it is written there",
                markup=False,
                highlight=False,
            )


def _bind(port: int) -> Any:
    """A server bound to 127.0.0.1:PORT that answers GET / with its `body` (set by `_serve`),
    404 elsewhere; bound before the page is made, so a port in use is the one message of a
    run that wrote nothing (docs/view.md)."""
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    class Page(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            if self.path not in ("/", "/index.html"):
                self.send_error(404)
                return
            body = getattr(self.server, "body", b"")
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, format: str, *args: object) -> None:
            pass  # no line per request

    try:
        return ThreadingHTTPServer((SERVE_HOST, port), Page)
    except OSError as exc:
        raise SsgError.single(f"cannot serve on {SERVE_HOST}:{port}: {exc.strerror}") from None


def _serve(server: Any, body: bytes) -> None:
    """The page, from memory, on http://127.0.0.1:PORT/ (for a browser on another machine,
    through an SSH tunnel), until Ctrl-C."""
    server.body = body
    err.print(
        f"serving on http://{SERVE_HOST}:{server.server_address[1]}/ (Ctrl-C stops)",
        markup=False,
        highlight=False,
    )
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        err.print("stopped", markup=False, highlight=False)
