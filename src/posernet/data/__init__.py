"""Data front end: the authors' JSON graphs, the synthetic simulator, storage and data modules."""

from .posernet_json import ESTIMATE_KEYS, SCENES, load_posernet_json, save_posernet_json

__all__ = ["ESTIMATE_KEYS", "SCENES", "load_posernet_json", "save_posernet_json"]
