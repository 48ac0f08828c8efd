"""retrieval.methods: the method presets, and the YAML files in configs/ that say the same."""

from __future__ import annotations

from pathlib import Path

import pytest

from cae_lcd.core.conf import load_conf_file
from cae_lcd.core.errors import ConfigError
from retrieval.detector import resolve_conf
from retrieval.methods import METHODS, method_conf

REPO = Path(__file__).parents[2]

PRESET_FILES = {"mild": "mild.yaml", "mild+verify": "mild_verify.yaml"}


class TestMethodConf:
    @pytest.mark.parametrize("method", list(PRESET_FILES))
    def test_yaml_presets_equal_the_methods(self, method):
        assert resolve_conf(load_conf_file(REPO / "configs" / PRESET_FILES[method])) == \
            resolve_conf(method_conf(method))

    def test_every_method_resolves(self):
        for method in METHODS:
            resolve_conf(method_conf(method))
        assert resolve_conf(method_conf("cae")) == resolve_conf({})

    def test_user_conf_on_top_and_unknown_method(self):
        conf = resolve_conf(method_conf("mild", {"policy": {"min_seq_score": 0.9}, "search": {"k": 3}}))
        assert conf["descriptor"]["name"] == "mild" and conf["policy"]["min_seq_score"] == 0.9
        assert conf["search"]["k"] == 3 and METHODS["mild"]["policy"]["min_seq_score"] == 0.7  # preset untouched
        with pytest.raises(ConfigError, match="unknown method 'fabmap'; known: cae, mild, mild\\+verify"):
            method_conf("fabmap")
