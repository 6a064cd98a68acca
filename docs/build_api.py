"""The API reference: pdoc (numpy docstrings) over gonio's public packages, into a folder.

    python docs/build_api.py docs/api        # what `make docs` runs

Every warning pdoc gives (a name in ``__all__`` that does not resolve, a docstring it cannot
parse, a module that fails to import) is printed and makes the build fail: the reference is
built with none (tests/test_docs_build.py builds it into a temporary folder in the suite).

Two things are done before pdoc walks the packages, as a user's own ``import`` would: every
module is imported (pdoc imports what it finds with subprocesses mocked, and h5py asks
``platform`` for the processor through one at import: "Suppressed execution of ['uname', '-p']"),
and ``gonio.bench``'s names, which load their module on first use (PEP 562), are resolved.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
import warnings
from pathlib import Path

#: The packages and modules documented (pdoc adds their submodules).
API_MODULES = ("gonio.models", "gonio.fitting", "gonio.fitting.formats", "gonio.fitting.plots", "gonio.fitting.render",
               "gonio.fitting.render.preview", "gonio.sim", "gonio.bench", "gonio.bench.plan.plans")


def _import_all(names) -> list[str]:
    """Import each module and every submodule of each package, resolving the names a package
    loads on first use; return the failures' lines."""
    problems = []
    for name in names:
        try:
            module = importlib.import_module(name)
        except Exception as exc:                       # noqa: BLE001  (said, and the build fails)
            problems.append(f"{name} does not import: {type(exc).__name__}: {exc}")
            continue
        for info in pkgutil.walk_packages(getattr(module, "__path__", []), prefix=f"{name}."):
            try:
                importlib.import_module(info.name)
            except Exception as exc:                   # noqa: BLE001
                problems.append(f"{info.name} does not import: {type(exc).__name__}: {exc}")
    for name, module in list(sys.modules.items()):
        if name.startswith("gonio") and module is not None:
            problems += _resolve_lazy_names(module)
    return problems


def _resolve_lazy_names(module) -> list[str]:
    """A package's ``__all__`` names that load on first use (a module ``__getattr__``), put in
    its namespace: pdoc reads the namespace, not ``__getattr__``."""
    problems = []
    for attr in getattr(module, "__all__", ()) if "__getattr__" in vars(module) else ():
        if attr not in vars(module):
            try:
                setattr(module, attr, getattr(module, attr))
            except AttributeError as exc:
                problems.append(f"{module.__name__}.__all__ names {attr!r}, which does not resolve: {exc}")
    return problems


def build(out, modules=API_MODULES) -> list[str]:
    """Render ``modules`` into the folder ``out``; return every warning (empty: a clean build)."""
    import matplotlib

    matplotlib.use("Agg")
    import pdoc
    import pdoc.render

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        problems = _import_all(modules)
    # what imports warn about (a dependency's deprecation) is theirs; pdoc's are the reference's
    problems += [f"import: {w.category.__name__}: {w.message}" for w in caught
                 if str(w.filename).startswith(str(Path(__file__).resolve().parents[1] / "gonio"))]
    pdoc.render.configure(docformat="numpy", show_source=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pdoc.pdoc(*modules, output_directory=Path(out))
    return problems + [f"pdoc: {w.message}" for w in caught]


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0] if argv else "docs/api")
    problems = build(out)
    for line in problems:
        print(f"warning: {line}", file=sys.stderr)
    if problems:
        print(f"docs: {len(problems)} warning(s); the reference in {out} is incomplete", file=sys.stderr)
        return 1
    print(f"docs: {out / 'index.html'} (0 warnings)")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))     # the checkout's gonio, as `make docs` runs it
    sys.exit(main())
