"""The ``carapost`` command.

Every sub-command prints a one-line ``carapost <command>: error: ...`` message and exits
with a non-zero status on failure; tracebacks are shown only with ``--debug``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence

__all__ = ["main", "CliError"]


class CliError(Exception):
    """A failure to report to the user as one line (no traceback)."""


def _cmd_gui(args: argparse.Namespace) -> dict:
    from carapost.ui.app import main as gui_main

    code = gui_main(args.files)
    if code:
        raise CliError(f"the application exited with status {code}")
    return {}


def _cmd_info(args: argparse.Namespace) -> dict:
    from carapost.commands.info import file_info, format_info

    infos = [file_info(p) for p in args.files]
    if not args.json:
        print("\n".join(format_info(i) for i in infos))
    return {"files": infos}


Command = Callable[[argparse.Namespace], dict]


def _parser() -> tuple[argparse.ArgumentParser, dict[str, Command]]:
    parser = argparse.ArgumentParser(prog="carapost", description="CaraPost for Python: facial motion capture.")
    common = argparse.ArgumentParser(add_help=False)
    g = common.add_argument_group("common options")
    g.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    g.add_argument("--json", action="store_true", help="print a machine-readable JSON summary last")
    g.add_argument("--no-progress", action="store_true", help="no progress bars (farm logs)")
    g.add_argument("--log", metavar="FILE", help="also write the log to FILE")
    sub = _Sub(parser.add_subparsers(dest="command"), common)
    commands: dict[str, Command] = {}

    from carapost.commands import batch, calibrate, convert_detect, demo, export, label, process

    p = sub.add_parser("gui", help="open the desktop application (the default with no command)")
    p.add_argument("files", nargs="*", help="a .cara, a .pico of a take, or one source per camera")
    commands["gui"] = _cmd_gui
    p = sub.add_parser("info", help="summarise .pico, .xcp/.qca/.toml, .cara, .c3d, video or image-folder files")
    p.add_argument("files", nargs="+")
    commands["info"] = _cmd_info
    commands.update(demo.add_parsers(sub))
    commands.update(convert_detect.add_parsers(sub))
    commands.update(export.add_parsers(sub))
    commands.update(calibrate.add_parsers(sub))
    commands.update(process.add_parsers(sub))
    commands.update(label.add_parsers(sub))
    commands.update(batch.add_parsers(sub))
    return parser, commands


class _Sub:
    """Sub-parser factory adding the common options to every command."""

    def __init__(self, sub: argparse._SubParsersAction, common: argparse.ArgumentParser) -> None:
        self._sub, self._common = sub, common

    def add_parser(self, name: str, **kw: object) -> argparse.ArgumentParser:
        return self._sub.add_parser(name, parents=[self._common], **kw)  # type: ignore[arg-type]


def _setup_logging(log_file: str | None) -> None:
    import logging

    logger = logging.getLogger("carapost")
    logger.setLevel(logging.INFO)
    if not any(isinstance(h, logging.StreamHandler) for h in logger.handlers):
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("carapost: %(levelname)s: %(message)s"))
        h.setLevel(logging.WARNING)
        logger.addHandler(h)
    if log_file:
        fh = logging.FileHandler(log_file, encoding="utf-8")
        fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        logger.addHandler(fh)


def main(argv: Sequence[str] | None = None) -> int:
    parser, commands = _parser()
    args = parser.parse_args(argv)
    if args.command is None:  # plain `carapost` opens the desktop application
        args = parser.parse_args(["gui"])
    if args.no_progress:
        from carapost.commands import progress

        progress.ENABLED = False
    try:
        _setup_logging(args.log)
    except OSError as exc:
        print(f"carapost {args.command}: error: cannot open the log file: {exc}", file=sys.stderr)
        return 1
    try:
        summary = commands[args.command](args)
    except (CliError, ValueError, OSError, KeyError) as exc:
        if args.debug:
            raise
        print(f"carapost {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"carapost {args.command}: cancelled", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(summary, default=str))
    if isinstance(summary, dict) and summary.get("cancelled"):
        return 130  # the conventional status of a run stopped by Ctrl+C (what was done is saved)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
