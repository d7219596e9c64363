"""Sphinx configuration of the tetdose documentation (``make docs``).

The pages are MyST markdown (the former README's sections), the command reference is generated
from :func:`tetdose.cli.build_parser` (sphinx-argparse), the API reference from the numpydoc
docstrings (autosummary), and the examples in ``examples/`` are executed by sphinx-gallery at
every build: an example that breaks fails the build (warnings are errors: ``-W --keep-going``).
"""

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("MPLBACKEND", "Agg")
# The examples run the CLI in subprocesses: they must import this checkout's code, and share one
# numba cache (compiled kernels are reused across processes and builds).
os.environ["PYTHONPATH"] = os.pathsep.join(
    p for p in (str(ROOT / "src"), os.environ.get("PYTHONPATH", "")) if p)
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))

import tetdose  # noqa: E402

project = "tetdose"
author = "the tetdose developers"
copyright = "the tetdose developers, BSD-3-Clause"  # noqa: A001
release = tetdose.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "numpydoc",
    "sphinxarg.ext",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "auto_examples/*.ipynb", "auto_examples/*.py", "**.codeobj.json"]
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3

autosummary_generate = True
autodoc_default_options = {"members": True, "inherited-members": False}
autodoc_typehints = "none"
numpydoc_show_class_members = False
numpydoc_validation_checks: set[str] = set()
numpydoc_xref_param_type = False

html_theme = "furo"
html_title = f"tetdose {release}"
html_static_path: list[str] = []

sphinx_gallery_conf = {
    "examples_dirs": str(ROOT / "examples"),
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/ex_",          # execute every example
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": False,    # all errors reported at the end; they fail the build
    "only_warn_on_example_error": False,
    "matplotlib_animations": False,
    "reference_url": {"tetdose": None},
}

nitpicky = False


def _plain_bars(app, what, name, obj, options, lines):  # noqa: ARG001
    """Docstrings write |x| for a norm or an absolute value; in reST that is a substitution.

    Escape the bars outside inline literals and literal blocks, so that the docstrings can keep
    their plain-text formulas and still build without a warning.
    """
    literal = False
    for i, line in enumerate(lines):
        stripped = line.strip()
        if literal and stripped and not line.startswith((" ", "\t")):
            literal = False
        if not literal and "|" in line:
            parts = line.split("``")
            lines[i] = "``".join(p.replace("|", r"\|") if k % 2 == 0 else p
                                 for k, p in enumerate(parts))
        if stripped.endswith("::"):
            literal = True


def setup(app):
    app.connect("autodoc-process-docstring", _plain_bars)
