"""The ``gonio perf`` (alias ``bench``) commands: model evaluation speed, fit speed against error,
measured materials against a plain fit (``gonio perf real``), plans' instrument time against
fit error (``gonio perf acquisition``). Each figure is a ratio
against a peer or a limit measured in the same run (gonio.perf)."""

from __future__ import annotations

import argparse
from pathlib import Path

from gonio.core.errors import GonioError

__all__ = ["real_files", "register"]


def _cmd_bench_models(args):
    try:
        from gonio.perf.models import run
    except ImportError:
        raise GonioError("this build of gonio.models has no benchmark") from None
    if not 1_000 <= args.n <= 10_000_000:
        raise GonioError(f"-n {args.n}: give a batch of direction pairs between 1000 and 10000000")
    run(n=args.n)


def _cmd_bench_fit(args):
    from gonio.perf.fit import run, run_real

    if args.real:
        files = [Path(f) for f in args.real]
        for f in files:
            if not f.is_file() or f.suffix.lower() not in (".bsdf", ".binary"):
                raise GonioError(f"--real {f}: give measured RGL .bsdf or MERL .binary files that exist")
        if args.quick:
            raise GonioError("--quick is for the synthetic matrix; --real fits each file in full")
        try:
            run_real(files, out=Path(args.out) if args.out else None, seed=args.seed)
        except ValueError as exc:
            raise GonioError(" ".join(str(exc).split())[:300]) from None
        return
    run(quick=args.quick, out=Path(args.out) if args.out else None)


def real_files(paths) -> list:
    """The measured files of ``paths`` (files, or folders whose .bsdf/.binary files are taken in name
    order); one line naming what to fix otherwise."""
    files = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in (".bsdf", ".binary"))
            if not found:
                raise GonioError(f"{str(p)!r}: the folder has no RGL .bsdf or MERL .binary file")
            files += found
        elif p.is_file() and p.suffix.lower() in (".bsdf", ".binary"):
            files.append(p)
        else:
            raise GonioError(f"{str(p)!r}: give measured RGL .bsdf or MERL .binary files, or folders of them")
    return files


def _cmd_bench_real(args):
    from gonio.perf.real import run_real

    import gonio.models as gm

    if args.peer != "same" and args.peer not in gm.names():
        raise GonioError(f"--peer {args.peer!r}: give a model family ({', '.join(gm.names())}) or 'same'")
    files = real_files(args.paths)
    try:
        run_real(files, out=Path(args.out) if args.out else None, seed=args.seed, peer=args.peer,
                 peer_eval=args.peer_eval, warm=not args.no_warm_up)
    except ValueError as exc:
        raise GonioError(" ".join(str(exc).split())[:300]) from None


def _cmd_bench_acquisition(args):
    import gonio.models as gm
    from gonio.bench.samples import load_sample
    from gonio.perf.acquisition import CHOOSE, check_plans, parse_seeds, run, run_seeds

    plans = check_plans(args.plans)
    seeds = parse_seeds(args.seeds) if args.seeds is not None else None
    if seeds is not None and args.seed is not None:
        raise GonioError("--seed and --seeds exclude each other: give one seed or several")
    if not 1 <= args.points <= 1053:
        raise GonioError(f"--points {args.points}: give the adaptive plan's budget between 1 and 1053 points")
    if args.model is not None and args.model not in (*gm.names(), CHOOSE):
        raise GonioError(f"--model {args.model!r}: give one of {', '.join((*gm.names(), CHOOSE))}")
    sample = load_sample(args.sample)
    kw = dict(model=args.model, points=args.points, errors=args.errors, out=Path(args.out) if args.out else None,
              budget_fraction=args.budget_fraction, estimate_angles=args.estimate_angles)
    if seeds is None:
        run(plans, sample, seed=args.seed or 0, **kw)
    else:
        if "dense" not in plans:
            raise GonioError("--seeds compares each plan with the dense grid of the same seed: give dense among --plans")
        run_seeds(plans, sample, seeds, **kw)


def register(sub, *, env, seed, parser_class):
    """Add ``perf`` (alias ``bench``) and its commands to ``sub``; return its sub-parsers (the
    operator commands add ``bench capture`` there). ``env``: the command wrapper that turns
    environment errors into one line; ``seed``: the seed argument type."""
    b = sub.add_parser("perf", aliases=["bench"], help="benchmarks: figures as ratios against a peer or a limit")
    bsub = b.add_subparsers(dest="bench_command", metavar="WHAT", parser_class=parser_class)
    bsub.required = True
    bm = bsub.add_parser("models", help="model evaluations per second next to Mitsuba's bsdf.eval")
    bm.add_argument("-n", type=int, default=1_000_000)
    bm.set_defaults(func=env(_cmd_bench_models))
    bf = bsub.add_parser("fit", help="fit speed against error: gonio vs scipy least_squares, CRLB efficiency")
    bf.add_argument("--quick", action="store_true", help="a small matrix (about 10 s)")
    bf.add_argument("--out", help="folder for the CSV table and the PNG plot (with --real: a .csv file or a folder)")
    bf.add_argument("--real", nargs="+", metavar="FILE",
                    help="measured materials (RGL .bsdf, MERL .binary): gonio's chosen fit beside a scipy log-loss "
                         "peer, Ngan and log errors on one dense grid, times from the same run")
    bf.add_argument("--seed", type=seed, default=0, help="seed of the fits' starts (with --real)")
    bf.set_defaults(func=env(_cmd_bench_fit))
    br = bsub.add_parser("real", help="measured materials: gonio's --model auto against a plain scipy roughplastic "
                                      "fit, Ngan and log errors, dE00 and wall time from the same run")
    br.add_argument("paths", nargs="+", metavar="DIR_OR_FILE",
                    help="RGL .bsdf or MERL .binary files, or folders holding them")
    br.add_argument("--out", help="a .csv file or a folder for the table")
    br.add_argument("--seed", type=seed, default=0, help="seed of the fits' starts")
    br.add_argument("--peer", default="roughplastic", metavar="FAMILY",
                    help="the plain fit's model family (default roughplastic; 'same': the family gonio chose)")
    br.add_argument("--peer-eval", choices=("gonio", "mitsuba"), default="gonio",
                    help="how the peer evaluates its model: gonio (gonio's compiled model.eval, the stronger peer; "
                         "default) or mitsuba (Mitsuba's own BSDF, as issue 35's plain fit does)")
    br.add_argument("--no-warm-up", action="store_true",
                    help="time the first material cold: without the untimed run of both sides on 400 of its samples "
                         "that pays the process's one-time costs (Dr.Jit's tracing) before the rows")
    br.set_defaults(func=env(_cmd_bench_real))
    ba = bsub.add_parser("acquisition", help="per plan: the simulated capture's instrument time against the fit's "
                                             "error against the truth (Ngan, log, dE00), and the front")
    ba.add_argument("--plans", default="quick,standard,adaptive",
                    help="plan presets, 'adaptive', 'alc' or 'ndf' (fitted with their design weights; "
                         "'adaptive-unweighted', 'alc-unweighted' without), or 'thinned' (their peer: the dense "
                         "plan thinned uniformly to the same budget, fitted as the dense grid is), separated by "
                         "commas (default quick,standard,adaptive)")
    ba.add_argument("--sample", help="the virtual sample: a sample TOML or a measured RGL .bsdf file (default the "
                                     "demo's glossy plastic)")
    ba.add_argument("--model", help="the family fitted (default the sample's own; roughplastic for a measured file; "
                                    "'choose': each plan's data choose among four by cross-validation)")
    ba.add_argument("--points", type=int, default=24, help="the adaptive plan's budget (default 24; thinned: about "
                                                             "as many points)")
    ba.add_argument("--budget-fraction", type=float, help="the sequential plans stop at this fraction of the "
                                                           "dense plan's instrument time, and thinned keeps as many "
                                                           "of its points as fit in it (dense must be in --plans)")
    ba.add_argument("--errors", default="typical", help="the simulator's error preset, every plan the same "
                                                         "(default typical; gonio plans lists them)")
    ba.add_argument("--seed", type=seed, default=None, help="seed of the captures and the fits (default 0)")
    ba.add_argument("--seeds", metavar="LIST", help="several seeds (10-13 or 10,12,15): every plan captured with each, "
                                                    "then each plan's errors against the dense grid of the same "
                                                    "seed, summarised with their intervals (dense must be in --plans)")
    ba.add_argument("--estimate-angles", action=argparse.BooleanOptionalAction, default=True,
                    help="every plan's fit estimates the instrument's shared angle errors (zero offsets, holder "
                         "tilt, wedge) from its data, as gonio fit --estimate-angles (default; "
                         "--no-estimate-angles for the studies before 2026-12-05)")
    ba.add_argument("--out", help="a .csv file or a folder for the table")
    ba.set_defaults(func=env(_cmd_bench_acquisition))
    return bsub
