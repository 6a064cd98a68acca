"""How ``gonio ... --help`` and the CLI's errors look: 80 columns at most, an example in every
command's help.

:class:`HelpFormatter` wraps help at the terminal's width up to 80 columns, keeps indented
lines (examples, tables) as written and refills the rest; :data:`EXAMPLES` holds each command's
examples (tests/bench/test_cli_help.py parses every one of them with the real parser, so an
example that stops working fails the suite); :func:`error_text` lays out an error: one line in
a pipe or a log (what scripts and the suite read), wrapped at the terminal's width on a
terminal.
"""

from __future__ import annotations

import argparse
import shutil
import textwrap

from gonio.cli.progress import on_terminal

__all__ = ["HelpFormatter", "EXAMPLES", "examples_epilog", "error_text", "help_width", "say"]

MAX_WIDTH = 80


def help_width() -> int:
    """The terminal's width up to 80 columns (80 where there is no terminal)."""
    return max(40, min(shutil.get_terminal_size((MAX_WIDTH, 24)).columns, MAX_WIDTH))


class HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter at most 80 columns wide; in descriptions and epilogs a paragraph
    whose lines are indented (examples, the exit status table) is kept as written, any other
    is refilled."""

    def __init__(self, prog, indent_increment=2, max_help_position=24, width=None):
        super().__init__(prog, indent_increment, max_help_position, width=width or help_width() - 2)

    def _format_usage(self, usage, actions, groups, prefix):
        # argparse keeps a group of alternatives on one line, however long: wrap what is
        # still too long at its spaces, under the usage's own indentation
        text = super()._format_usage(usage, actions, groups, prefix)
        out = []
        for line in text.split("\n"):
            if len(line) <= self._width:
                out.append(line)
                continue
            body = line.lstrip(" ")
            indent = " " * (len(line) - len(body))
            if line.startswith("usage: "):
                indent = " " * (len("usage: ") + len(self._prog) + 1)
            out += textwrap.wrap(line, self._width, subsequent_indent=indent, break_long_words=False,
                                 break_on_hyphens=False)
        return "\n".join(out)

    def _fill_text(self, text, width, indent):
        out = []
        for para in text.split("\n\n"):
            lines = para.splitlines()
            if any(line.startswith(" ") for line in lines[1:]) or (lines and lines[0].startswith(" ")):
                out.append("\n".join(indent + line for line in lines))
            else:
                out.append(textwrap.fill(" ".join(para.split()), width, initial_indent=indent,
                                         subsequent_indent=indent, break_on_hyphens=False))
        return "\n\n".join(out)


def error_text(line: str) -> str:
    """An error as printed: as given where stderr is a pipe or a file, wrapped at the
    terminal's width (80 columns at most, continuation lines indented) on a terminal."""
    if not on_terminal():
        return line
    return textwrap.fill(line, help_width(), subsequent_indent="  ", break_on_hyphens=False,
                         break_long_words=False)


def say(text: str, file=None) -> None:
    """Print a message (its lines): whole in a pipe or a file, one line a message as scripts and
    logs read it; wrapped at the terminal's width (80 columns at most) on a terminal, at spaces
    only, so a path or a command stays in one piece."""
    import sys

    stream = sys.stdout if file is None else file
    if on_terminal(stream):
        text = "\n".join(textwrap.fill(line, help_width(), subsequent_indent="  ", break_long_words=False,
                                       break_on_hyphens=False) or line for line in text.split("\n"))
    print(text, file=stream, flush=True)


#: Each command's examples, by its prog (``gonio fit``, ``gonio sim serve``): ``(command,
#: comment)``; a command may continue on the next line after `` \\``.
EXAMPLES: dict[str, list[tuple[str, str]]] = {
    "gonio": [
        ("gonio demo", "the whole loop on the simulated instrument"),
        ("gonio models", "the models a fit can use"),
        ("gonio plans", "the measurement plans and error presets"),
        ("gonio capture --sim --plan quick --out s1", "a simulated session"),
        ("gonio export s1", "s1/dataset.nc"),
        ("gonio fit s1/dataset.nc --out fit.json", "a model chosen by BIC"),
    ],
    "gonio demo": [
        ("gonio demo", "into ./gonio-out: calibrate, capture, fit, report"),
        ("gonio demo --plan quick --no-posterior --out demo", "a faster one"),
    ],
    "gonio capture": [
        ("gonio capture --sim --plan quick --out s1", "the simulator, the demo sample"),
        ("gonio capture --sim --sample gold --out s2", "an example sample"),
        ("gonio capture --sim --sample black-gloss --plan glossy \\\n    --errors typical --calibration cal.toml --out s3",
         ""),
        ("gonio capture --sim --plan adaptive --out s4", "chosen from the data"),
        ("gonio capture --sim --plan adaptive --budget-minutes 10 --out s6", "to a time budget"),
        ("gonio capture --sim --plan adaptive --criterion alc --out s7", "batches by predicted f_r"),
        ("gonio capture --sim --plan dense --dry-run", "count and duration only"),
        ("gonio capture --port /dev/ttyUSB0 --meter-port /dev/ttyUSB1 \\\n    --camera gphoto2 --sample-id S-1 "
         "--operator 'A. Tester' --out s5", ""),
        ("gonio capture --resume s1", "finish an interrupted session"),
    ],
    "gonio calibrate": [
        ("gonio calibrate --sim --errors typical --out cal.toml", "the simulator"),
        ("gonio calibrate --port /dev/ttyUSB0 --meter-port /dev/ttyUSB1 \\\n    --camera gphoto2 --out cal.toml",
         ""),
    ],
    "gonio export": [
        ("gonio export s1", "writes s1/dataset.nc"),
        ("gonio export s1 --colour-chart chart.dng", "colour matrix from a chart"),
        ("gonio export s1 --attr institution=NPL --attr title='Tile 7'", "CF attributes"),
    ],
    "gonio verify": [("gonio verify s1", "exit 0: every point intact")],
    "gonio fit": [
        ("gonio fit s1/dataset.nc --out fit.json", "--model auto: BIC"),
        ("gonio fit s1/dataset.nc --model roughplastic \\\n    --option distribution=ggx --posterior --out fit.json",
         ""),
        ("gonio fit paper.bsdf --model auto --scene overcast --out fit.json", ""),
        ("gonio fit --batch a.nc b.nc --model diffuse --out fits", "on Dask"),
    ],
    "gonio render": [
        ("gonio render fit.json --dataset s1/dataset.nc --out render", ""),
        ("gonio render fit.json --dataset s1/dataset.nc --out render --preview", ""),
    ],
    "gonio convert": [
        ("gonio convert fit.json --to mitsuba-xml --out scene/fit.xml", ""),
        ("gonio convert s1/dataset.nc --to csv --out s1.csv", ""),
        ("gonio convert fit.json --to netcdf --attr institution=NPL --out fit.nc", ""),
    ],
    "gonio report": [
        ("gonio report gonio-out", "gonio-out/report.html"),
        ("gonio report s1 --out s1-report.html", ""),
    ],
    "gonio models": [("gonio models", "")],
    "gonio plans": [("gonio plans", "")],
    "gonio settings": [("gonio settings show --settings lab.toml", "")],
    "gonio settings show": [
        ("gonio settings show", "the defaults, with units"),
        ("gonio settings show --settings lab.toml --operator 'A. Tester'", ""),
    ],
    "gonio sim": [("gonio sim serve --clock 10", "")],
    "gonio sim serve": [
        ("gonio sim serve", "prints the three ports"),
        ("gonio sim serve --sample gold --clock 10 --seed 3", "ten times faster"),
    ],
    "gonio estop": [("gonio estop --port /dev/ttyUSB0", "")],
    "gonio perf": [("gonio perf fit --quick", ""), ("gonio perf models -n 100000", ""),
                   ("gonio perf real ../shared/data/rgl", "measured materials against a plain fit")],
    "gonio perf models": [("gonio perf models -n 100000", "")],
    "gonio perf fit": [
        ("gonio perf fit --quick --out perf", "about 10 s"),
        ("gonio perf fit --real paper.bsdf --out real.csv", ""),
    ],
    "gonio perf capture": [("gonio perf capture --points 3 --skip-full", "")],
    "gonio perf acquisition": [
        ("gonio perf acquisition", "quick, standard and adaptive on the demo's plastic"),
        ("gonio perf acquisition --plans standard,dense,adaptive \\\n    --points 40 --out acq.csv", ""),
        ("gonio perf acquisition --plans dense,adaptive,alc \\\n    --budget-fraction 0.095 --sample paper_white_rgb.bsdf", ""),
    ],
    "gonio perf real": [
        ("gonio perf real ../shared/data/rgl --out real.csv", "every measured file of the folder"),
        ("gonio perf real paper_white_rgb.bsdf --peer same", "the peer fits the family gonio chose"),
        ("gonio perf real ../shared/data/rgl --peer-eval mitsuba", "the peer evaluates Mitsuba's own BSDF (issue 35's plain fit)"),
    ],
    "gonio devices": [("gonio devices --port /dev/ttyUSB0 --meter-port /dev/ttyUSB1", "")],
    "gonio home": [("gonio home --port /dev/ttyUSB0", "")],
    "gonio move": [
        ("gonio move --port /dev/ttyUSB0 --angles 30,0,30,180", "directions, deg"),
        ("gonio move --port /dev/ttyUSB0 --stage 15,0,0,30", "stage angles, deg"),
    ],
    "gonio jog": [("gonio jog --port /dev/ttyUSB0 --axis yaw --by 2", "")],
    "gonio shot": [
        ("gonio shot --port /dev/ttyUSB0 --meter-port /dev/ttyUSB1 \\\n    --camera gphoto2 --angles 30,0,30,180 "
         "--out shot1", ""),
    ],
}


def examples_epilog(prog: str) -> str:
    """The ``examples:`` block of ``prog``'s help ('' where it has none)."""
    rows = EXAMPLES.get(prog)
    if not rows:
        return ""
    lines = ["examples:"]
    for command, comment in rows:
        parts = command.split("\n")
        lines += [f"  {p}" for p in parts[:-1]]
        last = f"  {parts[-1]}"
        if comment and len(last) + 5 + len(comment) <= MAX_WIDTH - 2:
            last += f"   # {comment}"
        elif comment:
            lines.append(f"  # {comment}")
        lines.append(last)
    return "\n".join(lines)
