"""``annotator review DATASET``: accept or reject annotated scenes in the browser.

The page writes files, so it is served on 127.0.0.1 (this machine) unless ``--host`` says
otherwise; any other address requires a token in the page's address: ``--token``, or one
made up and printed when it is not given.
"""

from __future__ import annotations

import argparse
import time


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dataset", help="dataset folder (FORMAT.md), annotated with `annotator annotate`"
    )
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to serve on (default 127.0.0.1: this machine only); any other address "
        "requires a token",
    )
    parser.add_argument(
        "--port",
        type=int,
        default=8080,
        help="port, 1 to 65535 (default 8080; the next free one if it is taken)",
    )
    parser.add_argument(
        "--scene",
        default=None,
        help="the scene every page opens on (default: the first with a physics flag, else the "
        "first)",
    )
    parser.add_argument(
        "--token",
        default=None,
        help="token the page's address must carry (default: none on 127.0.0.1, a random one "
        "printed at start otherwise)",
    )


def start(args: argparse.Namespace):
    """Start the server and print where to open it; returns the running ``ReviewApp``."""
    from viewer.server.startup import check_port

    check_port(args.port)  # at once: before the seconds of importing viser and open3d
    from viewer.server.access import is_loopback, new_token
    from viewer.server.app import ReviewApp

    token = args.token
    if token is None and not is_loopback(args.host):
        token = new_token()
    app = ReviewApp(
        args.dataset, host=args.host, port=args.port, token=token, start_scene=args.scene
    )
    done, total = app.state.progress()
    annotated = sum(app.state.info(s).annotated for s in app.state.ids)
    print(f"review: {total} scenes ({done} reviewed) at {app.url}  (Ctrl-C to stop)", flush=True)
    if token is not None:
        print(
            "review: this address carries the page's token: pages opened without it are refused",
            flush=True,
        )
    if annotated == 0:
        print(
            f"review: no scene of {args.dataset} is annotated yet: "
            f"run `annotator annotate {args.dataset}` first",
            flush=True,
        )
    return app


def run(args: argparse.Namespace) -> int:
    app = None
    try:
        app = start(args)
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt as exc:
        if app is not None:
            app.stop()
            print("review: stopped; every decision is saved in the scenes' review.json")
        if type(exc) is not KeyboardInterrupt:  # SIGTERM: the command line reports it
            raise
    return 0
