"""Integrations with other libraries' optimisation loops (the top stage: nothing imports it).

Each is an optional extra and is imported only by name, never by ``import torchpref``:

* :mod:`torchpref.integrations.ax`: ``PreferenceGP`` inside Ax (``pip install 'torchpref[ax]'``);
* :mod:`torchpref.integrations.ax_recipes`: ready Ax objects for it (surrogate spec, PBO, BOPE and
  rating generation strategies, experiments, comparisons and ratings, best points and BOPE's trace);
* :mod:`torchpref.integrations.bofire`: a ``PreferenceGP`` surrogate for BoFire
  (``pip install 'torchpref[bofire]'``).

See docs/ax.md.
"""
