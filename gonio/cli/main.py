"""The ``gonio`` command line: a thin layer over library calls.

Every command has ``--help``, with examples, at most 80 columns wide (gonio/cli/helptext.py);
``gonio models`` and ``gonio plans`` list what exists. Errors the user can fix print one line
on stderr (``gonio: error: ...``; wrapped at the width of a terminal) and exit with status 2,
without a traceback; nothing half-written is left behind (every file is written to a temporary
name and renamed). A step that makes a person wait shows a progress bar on a terminal, and
nothing in a pipe or with ``--quiet`` (gonio/cli/progress.py).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gonio.cli.helptext import HelpFormatter, error_text, examples_epilog
from gonio.cli import commands
from gonio.core.errors import GonioError

__all__ = ["main", "build_parser", "walk_parsers"]


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (usage stays available through --help) and help at most
    80 columns wide, examples and tables kept as written."""

    def error(self, message):
        _say(f"gonio: error: {message} (see `{self.prog} --help`)")
        raise SystemExit(2)

    def _get_formatter(self):
        return HelpFormatter(prog=self.prog)


def _version() -> str:
    from importlib import metadata       # here, not at the top: `gonio estop` does not wait for it

    try:
        return metadata.version("gonio")
    except metadata.PackageNotFoundError:
        return "unknown"


def _seed(text: str) -> int:
    """A seed: an integer from 0 to 2**63 - 1 (numpy's generators take no negative seed)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid seed {text!r}: give an integer from 0 to 2**63 - 1") from None
    if not 0 <= value < 2 ** 63:
        raise argparse.ArgumentTypeError(f"seed {value} is out of range: give an integer from 0 to 2**63 - 1")
    return value


def _add_session_options(parser) -> None:
    parser.add_argument("--sample-id", help="the sample's identifier, recorded in session.toml and the report "
                                            "(or [session] sample_id in the settings)")
    parser.add_argument("--sample-description", help="what the sample is (recorded; shown in the report)")
    parser.add_argument("--operator", help="who measures (recorded; shown in the report)")


# --------------------------------------------------------------------------- parser
LOSS_HELP = ("chi2 (the data's Gaussian noise; default for dataset.nc), robust (pseudo-Huber on chi2's residuals), "
             "cosine (Ngan 2005 cosine-weighted L2), log (Loew 2012 ln(1 + f cos) residuals, sandwich covariance; "
             "default for RGL .bsdf and MERL .binary files, which carry no uncertainty), luminance (the error relative "
             "to the pair's measured luminance, cos-weighted: colour as a render weighs it), discrepancy (chi2 with a "
             "relative and absolute model-discrepancy variance fitted with the model; experimental); every loss "
             "weights each sample by its solid angle")
EXIT_OK, EXIT_FAILED, EXIT_REFUSED, EXIT_STOPPED = 0, 1, 2, 3

EPILOG = """exit status:
  0    done (a capture: every point of the plan measured)
  1    failed: an unexpected error (a bug: please report the traceback)
  2    refused: bad input or environment, said in one line; nothing was written
       or changed
  3    stopped, resumable: a capture stopped before the end (Ctrl-C, SIGTERM,
       SIGHUP, a fault, the lamp or a port lost); the session is consistent:
       `gonio capture --resume DIR`
  130  interrupted (Ctrl-C) outside a capture"""

QUIET_HELP = "no progress bar (there is none when stderr is not a terminal)"
ATTR_HELP = ("a global attribute of the NetCDF file (repeatable): CF's title, institution, source, history, "
             "references, comment, or an ACDD-1.3 one such as summary, creator_name, license; e.g. "
             "institution='NPL, Teddington'")


def _presets_text() -> str:
    """The plan presets' names, from gonio/bench/plan/presets (found without importing the
    plan module: ``gonio --help`` stays quick)."""
    import importlib.util

    spec = importlib.util.find_spec("gonio.bench.plan")
    folder = Path(next(iter(spec.submodule_search_locations))) / "presets"
    return ", ".join(sorted(p.stem for p in folder.glob("*.toml")))


def walk_parsers(parser, seen=None):
    """Every parser under ``parser`` (itself first), each once (an alias is the same parser)."""
    seen = set() if seen is None else seen
    if id(parser) in seen:
        return
    seen.add(id(parser))
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                child = action.choices[choice.dest]
                if child.description is None and choice.help:
                    child.description = choice.help[:1].upper() + choice.help[1:] + "."
                yield from walk_parsers(child, seen)


def _with_examples(parser) -> None:
    """Every parser's description (its one-line help) and examples (gonio/cli/helptext.py)."""
    for p in walk_parsers(parser):
        examples = examples_epilog(p.prog)
        if examples:
            p.epilog = f"{examples}\n\n{p.epilog}" if p.epilog else examples


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="gonio", description="Physically based BRDF measurement and validation bench.",
                epilog=EPILOG)
    p.add_argument("--version", action="version", version=f"gonio {_version()}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    d = sub.add_parser("demo", help="full loop on the simulated instrument: capture, export, fit, render, report")
    d.add_argument("--out", default="gonio-out", help="output folder (default ./gonio-out)")
    d.add_argument("--seed", type=_seed, default=1, help="seed of the simulated instrument and the fit (default 1)")
    d.add_argument("--plan", default="standard",
                   help=f"plan preset ({_presets_text()}; see `gonio plans`) or TOML/CSV file (default standard)")
    d.add_argument("--posterior", action=argparse.BooleanOptionalAction, default=True,
                   help="also sample the posterior with emcee (default on)")
    d.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    d.set_defaults(func=commands.cmd_demo)

    mo = sub.add_parser("models", help="list the models a fit can use, and the example samples")
    mo.set_defaults(func=commands.cmd_models)
    pl = sub.add_parser("plans", help="list the measurement plan presets and the simulator's error presets")
    pl.set_defaults(func=commands.cmd_plans)

    c = sub.add_parser("capture", help="run a capture session (simulated or real instrument)", epilog=EPILOG)
    c.add_argument("--sim", action="store_true", help="use the simulated instrument in this process")
    c.add_argument("--sample", help="simulated instrument only: an example sample's name (see `gonio models`), "
                                    "a sample TOML or a measured RGL .bsdf file (default: the demo's)")
    c.add_argument("--plan", default="standard",
                   help=f"preset ({_presets_text()}; see `gonio plans`), plan TOML/CSV file, adaptive "
                        "(chosen from the data) or ndf (NDF-seeded: retro-reflection first) (default standard)")
    c.add_argument("--points", type=int, metavar="N",
                   help="with --plan adaptive or ndf: the most points to measure (default 24)")
    c.add_argument("--budget-minutes", type=float, metavar="M",
                   help="with --plan adaptive, instead of --points: the most instrument time (motion, settling, "
                        "exposures, the preparation), in minutes; a batch is added only if the plan's estimate of "
                        "its time fits in what is left")
    c.add_argument("--target-rel-u", type=float, metavar="X",
                   help="with --plan adaptive: stop once every fitted parameter's relative 1-sigma is below X")
    c.add_argument("--target-de00", type=float, metavar="D",
                   help="with --plan adaptive: stop once a proxy of the colour's uncertainty is below D: the predicted "
                        "CIEDE2000 1-sigma of the fitted model's albedo colour (normal view, its RGB as linear sRGB, "
                        "D65) from the fit's parameter covariance; not a rendered colour difference")
    c.add_argument("--candidates", metavar="PLAN", help="with --plan adaptive: the plan it chooses from (default dense)")
    c.add_argument("--criterion", choices=["d-optimal", "alc"],
                   help="with --plan adaptive: how each batch is chosen: d-optimal (default: the fitted parameters' "
                        "uncertainty) or alc (the predicted variance of f_r cos over the hemisphere, with a "
                        "model-discrepancy term; docs/performance.md compares them)")
    c.add_argument("--out", help="new session folder")
    c.add_argument("--resume", metavar="DIR", help="finish an interrupted session")
    c.add_argument("--seed", type=_seed, default=0, help="seed (simulated noise and faults)")
    c.add_argument("--settings", help="instrument settings TOML overriding gonio/bench/instrument.toml")
    c.add_argument("--errors", choices=["ideal", "typical", "poor"],
                   help="simulated instrument's systematic errors (preset of [errors], see `gonio plans`; default: "
                        "the settings', else ideal)")
    c.add_argument("--calibration", metavar="CAL.toml",
                   help="calibration file from `gonio calibrate`: angles, reference factor and linearity applied")
    c.add_argument("--port", help="Zaber chain: serial port or pyserial URL (e.g. /dev/ttyUSB0, sim://NAME/zaber)")
    c.add_argument("--meter-port", help="SCPI power meter: serial port or pyserial URL")
    c.add_argument("--monochromator-port", help="Cornerstone monochromator (a spectral plan): serial port or URL")
    c.add_argument("--camera", help="camera: a serial port/URL of a simulated camera, folder:PATH, or gphoto2")
    c.add_argument("--dry-run", action="store_true", help="print point count, duration estimate, unreachable points; move nothing")
    c.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    _add_session_options(c)
    c.add_argument("--remeasure", metavar="POINTS",
                   help="with --resume: measure these plan points again, e.g. 3,7,10-12 (points whose RAW files "
                        "are missing or corrupt are measured again without asking)")
    c.add_argument("--rebuild-journal", action="store_true",
                   help="with --resume: replace a missing or damaged journal.sqlite, keeping the points whose RAW "
                        "files match their recorded checksums (the old journal is kept beside it)")
    c.add_argument("--restore-session", action="store_true",
                   help="with --resume: put back session.toml as the journal recorded it when the session started")
    c.set_defaults(func=commands.cmd_capture)

    cal = sub.add_parser("calibrate", help="estimate the bench's systematic errors (alignment: zero offsets and "
                         "holder tilt; detector linearity; the reference's non-Lambertian factor) into a file")
    cal.add_argument("--sim", action="store_true",
                     help="calibrate the simulated instrument (in this process, through the drivers and its sim:// ports)")
    cal.add_argument("--port", help="hardware: Zaber chain port or URL (mount the glossy artefact in the sample slot)")
    cal.add_argument("--meter-port", help="hardware: SCPI power meter port or URL")
    cal.add_argument("--camera", help="hardware: camera (a serial port/URL, folder:PATH, or gphoto2)")
    cal.add_argument("--errors", choices=["ideal", "typical", "poor"],
                     help="simulated instrument's error preset (see `gonio plans`; default: the settings' [errors], "
                          "else ideal)")
    cal.add_argument("--settings", help="instrument settings TOML overriding gonio/bench/instrument.toml")
    cal.add_argument("--seed", type=_seed, default=0, help="seed of the simulated instrument (its hidden errors and noise)")
    cal.add_argument("--out", required=True, help="calibration file to write (TOML)")
    cal.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    cal.set_defaults(func=commands.cmd_calibrate)

    e = sub.add_parser("export", help="write SESSION/dataset.nc from a session's journal")
    e.add_argument("session", help="session folder")
    e.add_argument("--colour-chart", metavar="DNG", help="a RAW capture of the ColorChecker in the holder's chart "
                   "slot: its fit gives the camera -> sRGB matrix and its uncertainty (default: the RAW files' "
                   "ColorMatrix1)")
    e.add_argument("--attr", action="append", default=[], metavar="KEY=VALUE", help=ATTR_HELP)
    e.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    e.set_defaults(func=commands.cmd_export)

    v = sub.add_parser("verify", help="which measured points of a session are intact, which damaged, and how to recover "
                       "(exit 0 all intact, 1 damage found, 2 bad input)")
    v.add_argument("session", help="session folder")
    v.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    v.set_defaults(func=commands.cmd_verify)

    f = sub.add_parser("fit", help="fit a model to a dataset")
    f.add_argument("dataset", nargs="+", help="dataset.nc, a MERL .binary or an RGL .bsdf file (several with --batch)")
    f.add_argument("--model", default="auto",
                   help="model name (see `gonio models`), or auto for BIC model selection (default)")
    f.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="model option, e.g. distribution=beckmann (repeatable)")
    f.add_argument("--out", required=True, help="fit file to write (JSON)")
    f.add_argument("--seed", type=_seed, default=0, help="seed of the multi-start and the sampler")
    f.add_argument("--loss", default=None, help=LOSS_HELP)
    f.add_argument("--colour-space", default="srgb", metavar="SPACE",
                   help="fit f_r in srgb (linear sRGB, D65: Mitsuba's rendering space; default), xyz (CIE XYZ) "
                        "or camera (white-balanced camera RGB); dataset.nc only")
    f.add_argument("--posterior", action=argparse.BooleanOptionalAction, default=False,
                   help="sample the posterior with emcee")
    f.add_argument("--estimate-angles", action=argparse.BooleanOptionalAction, default=None,
                   help="estimate the instrument's shared angle errors (stage zero offsets, holder tilt, wedge) that "
                        "the dataset's budget states, with the fit, and carry their posterior (chi2; dataset.nc). "
                        "Default: wherever the budget states them and the loss is chi2; --estimate-angles: refuse "
                        "a dataset or loss without them; --no-estimate-angles: never")
    f.add_argument("--batch", action="store_true", help="fit every DATASET on Dask; --out is then a folder")
    f.add_argument("--scene", metavar="SCENE",
                   help="model only what a scene needs: overcast, product-shot, close-up-sun or a Mitsuba scene file "
                        "(.xml, the sample's material <bsdf ... id=\"sample\">); each candidate is refitted to the "
                        "scene's pixels and rendered beside the measured material (RGL .bsdf or MERL .binary), and "
                        "the simplest one within --threshold is chosen")
    f.add_argument("--threshold", type=float, default=1.0, help="with --scene: mean CIEDE2000 a candidate must be "
                   "below (default 1)")
    f.add_argument("--scene-size", type=int, default=32, help="with --scene: render size in pixels (default 32)")
    f.add_argument("--scene-spp", type=int, default=256, help="with --scene: samples per pixel (default 256)")
    f.add_argument("--scene-light-samples", type=int, default=64,
                   help="with --scene: light samples a pixel for the pixel fit (default 64)")
    f.add_argument("--scene-time-limit", type=float, default=1800.0, metavar="SECONDS",
                   help="with --scene: seconds the scene's renders and pixel fits may take (default 1800)")
    f.add_argument("--scheduler", help="address of an existing Dask scheduler (default: a local cluster)")
    f.add_argument("--workers", type=int, default=2,
                   help="local Dask workers (default 2); the local cluster talks TLS with a certificate made for the run")
    f.add_argument("--dashboard", metavar="HOST:PORT",
                   help="serve the local cluster's Dask dashboard there, e.g. 127.0.0.1:8787 (default: none)")
    f.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    f.set_defaults(func=commands.cmd_fit)

    r = sub.add_parser("render", help="re-render a fit in Mitsuba at the dataset's geometry and compare")
    r.add_argument("fit", help="fit file (JSON)")
    r.add_argument("--dataset", required=True, help="dataset.nc")
    r.add_argument("--out", required=True, help="output folder (render.json)")
    r.add_argument("--variant", help="Mitsuba variant (default: llvm_ad_rgb when it works, else scalar_rgb)")
    r.add_argument("--preview", action="store_true", help="also render sphere previews under two lightings")
    r.add_argument("--measured", help="measured data to preview beside the fit: MERL .binary or RGL .bsdf")
    r.add_argument("--size", type=int, default=128, help="preview size in pixels (default 128)")
    r.add_argument("--spp", type=int, default=256, help="preview samples per pixel (default 256)")
    r.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    r.set_defaults(func=commands.cmd_render)

    cv = sub.add_parser("convert", help="exchange formats: a fit to Mitsuba XML/dict, MERL, PAB-Opto or Zemax, "
                                        "a dataset to CSV, MERL or PAB-Opto")
    cv.add_argument("source", help="fit file (JSON) or dataset.nc")
    cv.add_argument("--to", required=True, metavar="FORMAT",
                    choices=["mitsuba-xml", "mitsuba-xml-gonio", "mitsuba-dict", "merl", "csv", "merl-data", "pabopto",
                             "zemax", "netcdf", "astm", "rgl-bsdf"],
                    help="from a fit: mitsuba-xml (a file a plain Mitsuba 3 loads with mitsuba.load_file and "
                         "<include>: a model without a Mitsuba plugin is written as the closest native BSDF fitted "
                         "to it, its error printed), mitsuba-xml-gonio (gonio's own plugins, exact, for a process "
                         "that imports gonio), mitsuba-dict, "
                         "merl (the model resampled), pabopto (the model on a grid), zemax (Zemax/LightTools "
                         "tabular BSDF: OUT_brdf.bsdf, and OUT_btdf.bsdf for a model that transmits), rgl-bsdf (a fit "
                         "of an RGL-EPFL .bsdf file, written on that file's own grid for Mitsuba's measured plugin), netcdf (its "
                         "parameter table, value and uncertainties, as CF-1.8 NetCDF); from a dataset: csv, "
                         "merl-data (measured values binned, the rest no-data), pabopto (measured values); "
                         "pabopto writes one file per incident direction into the --out folder, for Radiance's "
                         "pabopto2bsdf")
    cv.add_argument("--out", required=True, help="file to write (a folder for --to pabopto); missing folders are made")
    cv.add_argument("--attr", action="append", default=[], metavar="KEY=VALUE",
                    help="with --to netcdf: " + ATTR_HELP)
    cv.set_defaults(func=commands.cmd_convert)

    rep = sub.add_parser("report", help="write a self-contained HTML report of an output folder")
    rep.add_argument("folder", help="folder with dataset.nc (and fit.json, render/render.json)")
    rep.add_argument("--out", help="report file (default FOLDER/report.html)")
    rep.add_argument("--approver", help="who approves the certificate (default: the settings' [session] approver; "
                                        "else a blank line to sign)")
    rep.add_argument("--approver-role", help="the approver's role (default: [session] approver_role)")
    rep.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    rep.set_defaults(func=commands.cmd_report)

    st = sub.add_parser("settings", help="instrument settings: show the effective values and where each came from")
    stsub = st.add_subparsers(dest="settings_command", metavar="WHAT", parser_class=_Parser)
    stsub.required = True
    show = stsub.add_parser("show", help="print the effective settings, each value with its unit and its source "
                                         "(default: gonio/bench/instrument.toml, file, option)")
    show.add_argument("--settings", help="instrument settings TOML overriding gonio/bench/instrument.toml")
    _add_session_options(show)
    show.set_defaults(func=commands.env(commands.cmd_settings_show))

    s = sub.add_parser("sim", help="the simulated instrument")
    ssub = s.add_subparsers(dest="sim_command", metavar="SIMCOMMAND", parser_class=_Parser)
    ssub.required = True
    serve = ssub.add_parser("serve", help="serve the simulated instrument on pseudo-terminals and print their paths")
    serve.add_argument("--sample", help="an example sample's name (see `gonio models`), a sample TOML or a measured "
                                        ".bsdf file")
    serve.add_argument("--seed", type=_seed, default=0)
    serve.add_argument("--settings", help="instrument settings TOML")
    serve.add_argument("--clock", default="realtime", help="instant, realtime, or a time scale factor such as 10")
    serve.add_argument("--faults", help="fault schedule TOML")
    serve.add_argument("--camera-size", metavar="SIZE",
                       help="the simulated camera's sensor: 24mp (6000x4000, 14-bit RGGB, a real camera's) or "
                            "WIDTHxHEIGHT; default the settings' [camera] (64x48 for tests)")
    serve.set_defaults(func=commands.cmd_sim_serve)

    es = sub.add_parser("estop", help="send the emergency stop to every Zaber device at once")
    es.add_argument("--port", required=True, help="Zaber chain port or URL")
    es.add_argument("--baud", type=int, default=115200)
    es.set_defaults(func=commands.cmd_estop)

    from gonio.cli.perf import register as _perf_commands      # perf models, fit, real
    from gonio.cli.operator import register as _operator_commands     # devices, home, move, jog, shot; bench capture

    bsub = _perf_commands(sub, env=commands.env, seed=_seed, parser_class=_Parser)

    _operator_commands(sub, bsub)
    _with_examples(p)
    return p


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["estop"]:            # the emergency stop first: nothing else loads on its path
        from gonio.cli import estop

        return estop.main(argv[1:])
    from gonio.bench.session.signals import SignalStop, startup_signals

    with startup_signals():              # SIGTERM/SIGHUP while gonio starts: said, never silent (issue 40)
        try:
            return _main(argv)
        except SignalStop as exc:
            _say(f"gonio: {exc} before it finished; nothing is left half-written")
            return 128 + exc.signum
        except Exception as exc:         # the stop raised inside what wraps it (a class's __set_name__
            stop = _stop_in(exc, SignalStop)     # in an import: RuntimeError from it, Python 3.11)
            if stop is None:
                raise
            _say(f"gonio: {stop} before it finished; nothing is left half-written")
            return 128 + stop.signum


def _stop_in(exc: BaseException, kind):
    """The first ``kind`` in ``exc``'s chain of explicit causes (``raise ... from``, as Python
    wraps an error from ``__set_name__``), or None. Not the implicit contexts: an error raised
    while a stop was being handled (a clean-up that failed) is that error, not the stop."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, kind):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__
    return None


def _main(argv) -> int:
    from gonio.bench.session.signals import SignalStop

    parser = build_parser()
    args = parser.parse_args(argv)
    from gonio.fitting import DataError
    from gonio.models import fast

    problem = fast.env_problem()
    if problem is not None:              # before any work: Dr.Jit reads them at its first kernel
        _say(f"gonio: error: {problem}")
        return EXIT_REFUSED
    from gonio.fitting import tune_allocator

    tune_allocator()                     # this process is gonio's: the allocator that fits need

    try:
        rc = args.func(args)
    except GonioError as exc:
        session = getattr(exc, "session_dir", None)
        if type(exc).__name__ == "CaptureInterrupted":      # Ctrl-C twice, SIGTERM, SIGHUP
            _say(f"gonio: stopped: {exc}")
            return EXIT_STOPPED
        if session is not None:                 # raised while measuring: the session stays resumable
            msg = str(exc)
            if f"--resume {session}" not in msg:
                msg += f" (the session is resumable: `gonio capture --resume {session}`)"
            _say(f"gonio: stopped: {msg}")
            return EXIT_STOPPED
        _say(f"gonio: error: {exc}")
        return EXIT_REFUSED
    except DataError as exc:
        _say(f"gonio: error: {' '.join(str(exc).split())}")
        return 2
    except FileNotFoundError as exc:
        _say(f"gonio: error: {exc.filename or exc}: no such file; check the path")
        return 2
    except BrokenPipeError:
        return commands.broken_pipe()
    except SignalStop:
        raise
    except KeyboardInterrupt:
        _say("gonio: interrupted")
        return 130
    return int(rc or 0)


def _say(line: str) -> None:
    """One line on stderr (wrapped at a terminal's width, gonio/cli/helptext.error_text); a
    closed terminal (SIGHUP) must not turn it into a traceback."""
    try:
        sys.stderr.write(error_text(line) + "\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
