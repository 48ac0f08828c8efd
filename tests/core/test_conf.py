import copy
from pathlib import Path

import pytest
import yaml

from cae_lcd.core.conf import ConfigError, Registry, dump_conf, load_conf_file, merge_conf

REPO = Path(__file__).parents[2]

DEFAULTS = {
    "a": 1,
    "section": {"x": 1.0, "y": "text", "inner": {"deep": [1, 2]}},
    "maybe": None,
}


class TestMergeConf:
    def test_non_strict_adds_keys(self):
        out = merge_conf({"a": 1, "s": {"x": 1}}, {"b": 2, "s": {"y": {"z": 3}}}, strict=False)
        assert out == {"a": 1, "b": 2, "s": {"x": 1, "y": {"z": 3}}}
        with pytest.raises(ConfigError, match="unknown config key 'b'"):
            merge_conf({"a": 1}, {"b": 2})

    def test_recursive_merge(self):
        out = merge_conf(DEFAULTS, {"a": 2, "section": {"inner": {"deep": [3]}}})
        assert out == {"a": 2, "section": {"x": 1.0, "y": "text", "inner": {"deep": [3]}}, "maybe": None}

    def test_none_override_and_none_section(self):
        assert merge_conf(DEFAULTS, None) == DEFAULTS
        assert merge_conf(DEFAULTS, {"section": None}) == DEFAULTS

    def test_unknown_key_names_dotted_path_and_allowed_keys(self):
        with pytest.raises(ConfigError) as err:
            merge_conf(DEFAULTS, {"section": {"inner": {"deap": 1}}})
        msg = str(err.value)
        assert "section.inner.deap" in msg
        assert "deep" in msg
        with pytest.raises(ConfigError) as err:
            merge_conf(DEFAULTS, {"bogus": 1})
        assert "'bogus'" in str(err.value)
        for key in ("a", "maybe", "section"):
            assert key in str(err.value)

    def test_where_prefix(self):
        with pytest.raises(ConfigError, match="gate.nope"):
            merge_conf({"x": 1}, {"nope": 2}, where="gate")

    def test_plain_value_for_section(self):
        with pytest.raises(ConfigError, match="section.inner"):
            merge_conf(DEFAULTS, {"section": {"inner": 5}})

    def test_inputs_not_mutated(self):
        before = copy.deepcopy(DEFAULTS)
        override = {"section": {"inner": {"deep": [9]}}, "maybe": {"k": [1]}}
        override_before = copy.deepcopy(override)
        out = merge_conf(DEFAULTS, override)
        assert DEFAULTS == before and override == override_before
        out["section"]["inner"]["deep"].append(7)
        out["maybe"]["k"].append(2)
        assert DEFAULTS == before and override == override_before


class TestLoadConfFile:
    def test_yaml_and_empty(self, tmp_path):
        (tmp_path / "a.yaml").write_text("policy:\n  min_inliers: 30\n")
        assert load_conf_file(tmp_path / "a.yaml") == {"policy": {"min_inliers": 30}}
        (tmp_path / "empty.yaml").write_text("")
        assert load_conf_file(tmp_path / "empty.yaml") == {}

    def test_errors(self, tmp_path):
        with pytest.raises(ConfigError, match="not found"):
            load_conf_file(tmp_path / "missing.yaml")
        (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
        with pytest.raises(ConfigError, match="mapping"):
            load_conf_file(tmp_path / "list.yaml")
        (tmp_path / "broken.yaml").write_text("a: [1, 2\n")
        with pytest.raises(ConfigError, match="cannot parse"):
            load_conf_file(tmp_path / "broken.yaml")

    @pytest.mark.parametrize("text, fragment", [
        ("search: {k: 3}\npolicy: {min_inliers: 20}\nsearch: {k: 4}\n", "key 'search' given twice (line 3)"),
        ("search:\n  k: 3\n  k: 4\n", "key 'k' given twice (line 3)"),
        ("a: " + "[" * 5000 + "]" * 5000 + "\n", "nested more than 32 levels deep"),  # was a RecursionError
        ("a: " + "{b: " * 40 + "1" + "}" * 40 + "\n", "nested more than 32 levels deep"),
    ], ids=["section twice", "key twice", "deep lists", "deep mappings"])
    def test_ambiguous_or_too_deep_refused_in_one_line(self, tmp_path, text, fragment):
        (tmp_path / "c.yaml").write_text(text)
        with pytest.raises(ConfigError, match="cannot parse config file") as err:
            load_conf_file(tmp_path / "c.yaml")
        assert fragment in str(err.value) and "\n" not in str(err.value)

    def test_anchors_and_merge_keys_still_work(self, tmp_path):
        (tmp_path / "c.yaml").write_text("base: &b {k: 3, min_score: 0.1}\nsearch: {<<: *b, k: 5}\n")
        assert load_conf_file(tmp_path / "c.yaml")["search"] == {"k": 5, "min_score": 0.1}

    def test_every_preset_loads(self):
        for path in sorted((REPO / "configs").glob("*.yaml")):
            assert isinstance(load_conf_file(path), dict), path


class TestDumpConf:
    def test_round_trip_keeps_order(self, tmp_path):
        conf = {"z": 1, "a": {"c": None, "b": [1.5, 2]}}
        dump_conf(conf, tmp_path / "c.yaml")
        text = (tmp_path / "c.yaml").read_text()
        assert text.index("z:") < text.index("a:")
        assert yaml.safe_load(text) == conf


class TestRegistry:
    def test_register_get_names(self):
        reg = Registry("widget")

        @reg.register("b")
        class B:
            pass

        @reg.register("a")
        class A:
            pass

        assert reg.get("a") is A and reg.get("b") is B
        assert reg.names() == ["a", "b"]
        with pytest.raises(ConfigError, match="unknown widget 'c'; available: a, b"):
            reg.get("c")
        with pytest.raises(ValueError, match="twice"):
            reg.register("a")(B)


class TestPresets:
    """``--config paper``: a bare name is a shipped preset, wherever the package is installed."""

    def test_a_bare_name_is_a_preset(self, tmp_path, monkeypatch):
        from cae_lcd.core.conf import PRESETS_DIR, load_conf_file, presets

        monkeypatch.chdir(tmp_path)  # outside the repository: no configs/ here
        assert {"default", "paper", "mild", "mild_verify", "train"} <= set(presets())
        assert load_conf_file("paper") == load_conf_file(PRESETS_DIR / "paper.yaml") != {}
        (tmp_path / "paper").write_text("search: {k: 3}\n")  # a file of that name wins
        assert load_conf_file("paper") == {"search": {"k": 3}}
        with pytest.raises(ConfigError, match=r"config file not found: nope \(presets: default, mild"):
            load_conf_file("nope")
        with pytest.raises(ConfigError, match=r"config file not found: sub/paper$"):
            load_conf_file("sub/paper")
