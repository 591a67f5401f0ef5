"""``tambridge view``: a finished run's splat viewer (``report/viewer/``) on a local web server at 127.0.0.1.

The server serves the run's ``report/`` folder, read only, to this machine alone; it is the same page the report
embeds and that opens from the file system, for browsers or setups that refuse ``file://`` pages.
"""

from __future__ import annotations

import functools
import http.server
import logging
import threading
import time
from pathlib import Path

from tambridge.errors import ViewerError
from tambridge.export.web_viewer import RUN_VIEWER_FOLDER
from tambridge.run_folder import FINISHED_MARKER
from tambridge.stop import RunStopped, StopRequests

logger = logging.getLogger("tambridge.pipelines.view")

HOST = "127.0.0.1"
"""The only address the server listens on: the viewer is for this machine's browser."""


def check_run_viewer(run_dir: Path) -> Path:
    """``run_dir/report/viewer/index.html`` of a finished run; a one-line :class:`ViewerError` naming what is
    missing otherwise."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ViewerError(f"{run_dir}: not a folder; pass the -o folder of a 'tambridge reconstruct' run")
    if not (run_dir / FINISHED_MARKER).is_file():
        raise ViewerError(f"{run_dir}: holds no finished run (no {FINISHED_MARKER}); wait for the run to finish, or "
                          "pass the -o folder of a finished 'tambridge reconstruct' run")
    index = run_dir / RUN_VIEWER_FOLDER / "index.html"
    if not index.is_file():
        raise ViewerError(f"{index}: not found; the run wrote no Gaussian map (mapper.enabled=false) or was made by a "
                          "tambridge without the viewer: run reconstruct again")
    return index


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    """Static files; requests go to the log at debug level instead of stderr."""

    def log_message(self, format, *args) -> None:  # the base class names its argument format
        logger.debug("%s %s", self.address_string(), format % args)


class ViewerServer(http.server.ThreadingHTTPServer):
    """An HTTP server of one run's ``report/`` folder on 127.0.0.1; ``url`` is the viewer's address.

    Use as a context manager (closes the socket); :meth:`serve_until_stopped` serves until SIGINT or SIGTERM.
    """

    daemon_threads = True  # a browser's open keep-alive connection must not hold up stopping the server

    def __init__(self, run_dir: Path, port: int = 0) -> None:
        """``port``: 0 takes a free one. Raises :class:`ViewerError` for a folder without a finished run's viewer or
        a port that cannot be bound."""
        index = check_run_viewer(run_dir)
        report_dir = Path(run_dir) / RUN_VIEWER_FOLDER.parent
        handler = functools.partial(_QuietHandler, directory=str(report_dir))
        try:
            super().__init__((HOST, port), handler)
        except OSError as error:
            raise ViewerError(f"{HOST}:{port}: cannot listen there ({error.strerror or error}); pass another --port, "
                              "or 0 for a free one") from None
        self.url = f"http://{HOST}:{self.server_address[1]}/{index.relative_to(report_dir).as_posix()}"
        """The viewer page's address."""

    def serve_until_stopped(self) -> None:
        """Serve until SIGINT (Ctrl-C) or SIGTERM, with tambridge's own handlers: a shell starts a background job
        with SIGINT ignored, which Python's Ctrl-C handling keeps."""
        # Requests are served from a thread while this one, where Python runs signal handlers, waits: socketserver
        # catches any Exception raised while it hands a request over, so a stop raised there would be lost.
        serving = threading.Thread(target=self.serve_forever, name="tambridge-viewer", daemon=True)
        try:
            with StopRequests() as stops, stops.deferred():
                serving.start()
                while stops.requested is None:
                    time.sleep(0.1)
        except RunStopped:  # a second signal while the first was being noted
            pass
        if serving.is_alive():
            self.shutdown()
