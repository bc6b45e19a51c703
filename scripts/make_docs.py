"""The API reference: HTML from the docstrings, with pdoc (pinned in requirements-dev.txt).

    make docs            (or: .venv/bin/python scripts/make_docs.py --output out/docs/api)

Documents ``hybrid_raycast.api`` (the script API), ``hybrid_raycast.core`` with every
submodule (the pure-numpy core: structures, planning, scene files, Dask, sensors,
point-cloud files), ``hybrid_raycast.operators.query`` (the queries ``api`` re-exports) and
``hybrid_raycast.operators.scan`` (``ScanResult``, ``write_scan``,
the sensor settings).  The repository root is the package, so it is imported as
``hybrid_raycast`` through a temporary folder holding a symlink to it (as Dask's workers
import it, ``scripts/_package.py``); ``api`` and ``operators`` import bpy, which the venv
has.

Exits 1 when pdoc fails, or warns that it cannot find or import a module (the page would
be missing), printing why; other pdoc warnings (an annotation it cannot resolve, say) are
printed and do not fail.  Exits 0 with the path of the index page otherwise.
"""

import argparse
import importlib
import pkgutil
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import ROOT, importable_by_workers  # noqa: E402

#: what the reference documents; every submodule of a package here is added too (pdoc
#: itself walks only the submodules a package's ``__all__`` names)
MODULES = ("hybrid_raycast.api", "hybrid_raycast.core", "hybrid_raycast.operators.query", "hybrid_raycast.operators.scan")
#: how pdoc 16's warnings begin when a module cannot be found or imported (pdoc/extract.py, pdoc/doc.py)
IMPORT_FAILURES = ("Cannot find spec", "Error importing", "Error loading", "Couldn't import", "The module specification")


def specs() -> list[str]:
    """MODULES plus each submodule pdoc would not reach by itself, each once.  Every module
    is imported here first, so an import error fails with its traceback."""
    import pdoc.extract

    wanted = []
    for name in MODULES:
        mod = importlib.import_module(name)
        wanted.append(name)
        if hasattr(mod, "__path__"):
            wanted += sorted(m.name for m in pkgutil.walk_packages(mod.__path__, prefix=name + "."))
    out = []
    for name in wanted:
        importlib.import_module(name)
        if not out or name not in pdoc.extract.walk_specs(out):
            out.append(name)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output", type=Path, default=ROOT / "out" / "docs" / "api", help="folder for the HTML (created)")
    args = ap.parse_args(argv)

    import pdoc
    import pdoc.render

    importable_by_workers()  # `import hybrid_raycast` finds this checkout
    # api's names are imported on first use (PEP 562), which pdoc does not do: resolve them
    api = importlib.import_module("hybrid_raycast.api")
    for name in api.__all__:
        setattr(api, name, getattr(api, name))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warnings.filterwarnings("ignore", category=DeprecationWarning, module="bpy")
        try:
            names = specs()
            pdoc.render.configure(docformat="restructuredtext", show_source=True,
                                  footer_text="Hybrid Ray Cast: make docs")
            pdoc.pdoc(*names, output_directory=args.output)
        except Exception as e:
            for w in caught:
                print(f"make_docs: warning: {w.message}", file=sys.stderr)
            print(f"make_docs: error: pdoc failed: {type(e).__name__}: {e}", file=sys.stderr)
            return 1
    failures = [w for w in caught if str(w.message).startswith(IMPORT_FAILURES)]
    for w in caught:
        print(f"make_docs: {'error' if w in failures else 'note'}: {w.category.__name__}: {w.message}", file=sys.stderr)
    if failures:
        print(f"make_docs: error: pdoc could not import {len(failures)} module(s); see above", file=sys.stderr)
        return 1
    pages = sorted(args.output.rglob("*.html"))
    print(f"make_docs: wrote {len(pages)} pages from {len(names)} module specs; open {args.output / 'index.html'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
