"""``gonio estop``: the emergency stop, on the shortest path from the key press to the stages.

The command is dispatched before anything else of ``gonio`` loads (`gonio.cli.main.main` hands
its arguments here first): its own small parser, then `gonio.bench.drivers.zaber.emergency_stop`,
which imports pyserial and the Zaber protocol and nothing heavier (no numpy, SciPy, Mitsuba or
fitting stack: issue 40 measured 3.1-3.9 s when it waited for them). ``/0 0 estop`` goes out
as soon as the port is open; the answers are counted afterwards.
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["main", "parser"]

#: exit statuses: sent and answered; sent but no device answered; the port or the input is bad
EXIT_SENT, EXIT_UNANSWERED, EXIT_REFUSED = 0, 1, 2


def parser(prog: str = "gonio estop") -> argparse.ArgumentParser:
    """The command's arguments (the same as in ``gonio --help``'s listing); its help as every
    command's (gonio/cli/helptext.py: 80 columns, an example; argparse and textwrap only)."""
    from gonio.cli.helptext import HelpFormatter, examples_epilog

    p = argparse.ArgumentParser(prog=prog, description="Send the emergency stop to every Zaber device at once.",
                                epilog=examples_epilog(prog), formatter_class=HelpFormatter)
    p.add_argument("--port", required=True, help="Zaber chain port or URL")
    p.add_argument("--baud", type=int, default=115200)
    return p


def run(port: str, baud: int = 115200) -> int:
    """Send the stop; print what happened; return the exit status."""
    from gonio.bench.drivers.zaber import emergency_stop
    from gonio.core.errors import GonioError

    try:
        n = emergency_stop(port, baudrate=baud)
    except GonioError as exc:
        sys.stderr.write(f"gonio: error: {exc}\n")
        return EXIT_REFUSED
    if n:
        print(f"emergency stop sent to every device ({n} answered)", flush=True)
        return EXIT_SENT
    print("emergency stop sent to every device, but none answered: check the stages have stopped", flush=True)
    return EXIT_UNANSWERED


def main(argv: list[str]) -> int:
    """``gonio estop ARGS``: parse and send (argparse's errors exit 2)."""
    class _Parser(argparse.ArgumentParser):
        def error(self, message):
            sys.stderr.write(f"gonio: error: {message} (see `gonio estop --help`)\n")
            raise SystemExit(EXIT_REFUSED)

    p = parser()
    p.__class__ = _Parser
    args = p.parse_args(argv)
    return run(args.port, args.baud)
