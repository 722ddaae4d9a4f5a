"""``annotator review DATASET``: accept or reject annotated scenes in the browser."""

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
        help="address to serve on (default 127.0.0.1: this machine only)",
    )
    parser.add_argument("--port", type=int, default=8080, help="port (default 8080)")


def run(args: argparse.Namespace) -> int:
    from viewer.app import ReviewApp

    app = ReviewApp(args.dataset, host=args.host, port=args.port)
    done, total = app.state.progress()
    annotated = sum(app.state.info(s).annotated for s in app.state.ids)
    print(
        f"review: {total} scenes ({done} reviewed) at http://{args.host}:{app.port}  (Ctrl-C to stop)"
    )
    if annotated == 0:
        print(
            f"review: no scene of {args.dataset} is annotated yet: run `annotator annotate {args.dataset}` first"
        )
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        app.stop()
        print("review: stopped; every decision is saved in the scenes' review.json")
    return 0
