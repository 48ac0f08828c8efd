"""Detection methods by name: the conf each one sets on top of the defaults (``cae-lcd detect --method``).

- ``cae``: the default detector (the CAE code, calibrated; ``configs/default.yaml``).
- ``mild``: MILD (Han & Fang 2017) as the paper describes it: ORB + multi-index hashing + Bayesian filter, a loop
  where a place's posterior exceeds 0.7 (``configs/mild.yaml``).
- ``mild+verify``: MILD's hypotheses, then SIFT matching and the geometric check (``configs/mild_verify.yaml``).

A user's own conf (``--config``) merges on top of the method's.
"""

from __future__ import annotations

import copy
from typing import Any

from cae_lcd.core.conf import ConfigError, merge_conf

__all__ = ["METHODS", "method_conf"]

_MILD: dict[str, Any] = {"descriptor": {"name": "mild"}, "whitening": {"enabled": False},
                         "temporal": {"name": "bayes"}, "calibration": {"enabled": False}}

#: method name -> conf overrides (the YAML presets in configs/ say the same, checked by a test)
METHODS: dict[str, dict[str, Any]] = {
    "cae": {},
    "mild": merge_conf(_MILD, {"policy": {"verify": False, "min_seq_score": 0.7}}, strict=False),
    "mild+verify": _MILD,
}


def method_conf(method: str, conf: dict[str, Any] | None = None) -> dict[str, Any]:
    """The conf of ``method`` with the user's ``conf`` merged on top (not yet resolved onto the defaults).

    Raises:
        ConfigError: an unknown method (named, with the known ones).
    """
    if method not in METHODS:
        raise ConfigError(f"unknown method {method!r}; known: {', '.join(METHODS)}")
    return merge_conf(copy.deepcopy(METHODS[method]), conf, strict=False)
