"""``gonio convert``: exchange formats (`gonio.bench.dataset.convert`). A fit -> Mitsuba XML (a
plain Mitsuba's, or with gonio's plugins) / dict JSON / MERL / PAB-Opto / CF-1.8 NetCDF (its
parameter table, `gonio.bench.dataset.cf.fit_netcdf`); a dataset -> CSV / MERL (binned) /
PAB-Opto."""

from __future__ import annotations

from pathlib import Path

from gonio.bench.dataset.convert import convert
from gonio.core.errors import GonioError

__all__ = ["convert_cli"]


def convert_cli(source: Path, out: Path, to: str, attrs=None) -> None:
    """``gonio convert SOURCE --to FORMAT --out OUT``: the library's conversion, its lines printed.
    ``attrs``: ``--attr KEY=VALUE`` pairs, the NetCDF's global attributes (``--to netcdf`` only)."""
    if to != "netcdf":
        if attrs:
            raise GonioError("--attr sets a NetCDF file's global attributes: use it with --to netcdf")
        convert(source, out, to, say=print)
        return
    from gonio.bench.dataset.cf import fit_netcdf, parse_attributes
    from gonio.core.preflight import check_output_file

    try:
        given = parse_attributes(attrs)
    except ValueError as exc:
        raise GonioError(str(exc)) from None
    if not Path(source).is_file():
        raise GonioError(f"{source} does not exist; give a fit file (JSON) written by gonio fit")
    if Path(source).suffix.lower() == ".nc":
        raise GonioError(f"{source} is a dataset, already CF-1.8 NetCDF; --to netcdf converts a fit file "
                         "(gonio export --attr KEY=VALUE sets a dataset's global attributes)")
    check_output_file(Path(out), "NetCDF file (--out)")
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    try:
        path = fit_netcdf(source, out, given)
    except ValueError as exc:
        raise GonioError(" ".join(str(exc).split())[:300]) from None
    print(f"wrote {path} (the fit's parameter table, CF-1.8)")
