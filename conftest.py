"""Repository-wide pytest set-up (tests/conftest.py holds the test fixtures).

Set before any test or notebook runs, so the Jupyter kernels that nbmake starts for
notebooks/*.ipynb inherit them:

* ``CAMO_SBI_SCALE=small``: every notebook's parameters cell picks its quick settings
  (a value already in the environment wins, e.g. ``CAMO_SBI_SCALE=full pytest --nbmake notebooks``);
* ``MPLBACKEND=Agg``: no GUI backend, whatever the developer's environment says.
"""

import os

os.environ.setdefault("CAMO_SBI_SCALE", "small")
os.environ["MPLBACKEND"] = "Agg"
