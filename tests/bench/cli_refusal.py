"""What the CLI refusal tests share: run ``gonio`` in this process, require one line and exit
status 2, list a folder, and make a quick simulated session with its dataset.nc and a diffuse
fit (tests/bench/test_cli_env_errors.py, tests/bench/test_injection.py)."""

from pathlib import Path

from gonio.cli import main as cli


def gonio(capsys, *args):
    """(exit status, the stderr lines) of ``gonio ARGS`` in this process."""
    rc = cli.main([str(a) for a in args])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    return rc, err


def refused(capsys, *args, needles=()):
    """``gonio ARGS`` exits 2 with one line on stderr naming each of ``needles``; returns it."""
    rc, err = gonio(capsys, *args)
    assert rc == 2, (rc, err)
    assert len(err) == 1, err
    assert err[0].startswith("gonio: error:"), err
    for needle in needles:
        assert needle in err[0], err[0]
    return err[0]


def listing(folder):
    return sorted(str(p.relative_to(folder)) for p in Path(folder).rglob("*"))


def quick_session(root: Path) -> dict:
    """A quick simulated session in ``root``, its dataset.nc and a diffuse fit of it."""
    from gonio.bench.dataset.export import export
    from gonio.bench.samples import load_sample
    from gonio.cli.capture import capture_sim
    from gonio.cli.fit import fit_cli

    capture_sim(root / "session", sample=load_sample(None), plan="quick", seed=1, progress=False)
    dataset = export(root / "session")
    fit_cli(dataset, model="diffuse", options=[], out=root / "fit.json", seed=0, loss="chi2", posterior=False)
    return {"session": root / "session", "dataset": dataset, "fit": root / "fit.json", "root": root}
