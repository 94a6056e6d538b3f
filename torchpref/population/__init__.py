"""Population priors: the mean utility of many people and how far a person departs from it
(:func:`fit_population`, :class:`Population`, ``save_population`` / ``load_population``)."""
