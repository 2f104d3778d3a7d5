"""Repository-wide pytest set-up (tests/conftest.py holds the test fixtures).

Set before any test or notebook runs, so the Jupyter kernels that nbmake starts for
notebooks/*.ipynb inherit them:

* ``CAMO_SBI_SCALE=small``: every notebook's parameters cell picks its quick settings
  (a value already in the environment wins, e.g. ``CAMO_SBI_SCALE=full pytest --nbmake notebooks``);
* ``MPLBACKEND=Agg``: no GUI backend, whatever the developer's environment says.

The default tier executes only the quickstart notebook; the other notebooks are in the slow
tier (`SLOW_NOTEBOOKS`, marked here because nbmake items carry no marks of their own): each
starts a Jupyter kernel that imports torch and sbi and runs a small study, a large share of the
default tier's time on a machine whose imports are slow (measured in
docs/getting-started/install.md). `.ci/run` still runs them.
"""

import os

import pytest

os.environ.setdefault("CAMO_SBI_SCALE", "small")
os.environ["MPLBACKEND"] = "Agg"

SLOW_NOTEBOOKS = ("02_reproduce_manipulator.ipynb", "03_block_stacking.ipynb", "04_method_comparison.ipynb",
                  "05_which_reach_next.ipynb", "06_lab_session.ipynb")


@pytest.hookimpl(tryfirst=True)  # before `-m 'not slow'` deselects by marks
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.suffix == ".ipynb" and item.path.name in SLOW_NOTEBOOKS:
            item.add_marker(pytest.mark.slow)
