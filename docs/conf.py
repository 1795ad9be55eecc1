"""Sphinx configuration of plenocl's documentation site (``pip install ".[docs]"``, then
``sphinx-build -W -b html docs docs/_build``; CI builds it with warnings as errors).

The site is the user guide (the README, batch runs, errors, the design and the
architecture, all Markdown through MyST) and the API reference generated from the
numpydoc docstrings (``api.rst``: autosummary over the package, each object documented
in the module that defines it).
"""

import inspect
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a source checkout

from plenocl.version import __version__  # noqa: E402

project = "plenocl"
author = "the plenocl developers"
release = version = __version__
extensions = ["sphinx.ext.autodoc", "sphinx.ext.autosummary", "numpydoc", "myst_parser"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "__pycache__"]
# every object once, on the page of the module that defines it (the package's re-exports
# would document it twice and make its name ambiguous)
autosummary_generate = True
autosummary_ignore_module_all = True
autodoc_default_options = {"members": True, "ignore-module-all": True}
numpydoc_show_class_members = False
myst_heading_anchors = 3
html_theme = "alabaster"
html_title = f"plenocl {release}"


def _skip_foreign(app, what, name, obj, skip, options):
    """Leave out what a module imports from elsewhere (SciPy's ``cKDTree``, a ``tuple``
    type alias, which ``inspect`` takes for a class): autodoc cannot tell a compiled
    class's or an alias's home, and autosummary would list it as the module's class."""
    home = str(getattr(obj, "__module__", None) or "")
    foreign = home and not home.startswith("plenocl")
    if foreign and (what == "module" or inspect.isclass(obj)):
        return True
    return skip


def setup(app):
    app.connect("autodoc-skip-member", _skip_foreign)
