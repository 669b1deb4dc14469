"""Data front end: the authors' JSON graphs, the synthetic simulator, storage and data modules."""
